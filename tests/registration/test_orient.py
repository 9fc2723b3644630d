"""The orient stage: given or proposed ups, snapping to a plane, the floor, proposed headings."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.data.camera import camera_at
from catalign.data.shapes import Shape
from catalign.data.views import Floor, render_view, upright_rotation
from catalign.features.orientation import Proposal
from catalign.geometry.levelling import even_headings
from catalign.geometry.se3 import axis_angle, make_pose
from catalign.registration.prepare.floor import floor_mask
from catalign.registration.prepare.orient import (
    Oriented,
    OrientOptions,
    SearchedUp,
    orient,
    snap_to_plane,
)
from catalign.registration.prepare.validation import MIN_VOXELS
from catalign.registration.results import Orientation
from catalign.registration.stages.describe import rotations_of

WORLD_UP = np.array([0.0, 0.0, 1.0])
VOXEL = 0.025


class FixedProposer:
    """Proposes the given ups (each with its score, 1 / rank when not given), and the given
    headings (each with its score, 0.5 when not given) under every up."""

    def __init__(
        self,
        ups: list[np.ndarray],
        headings: list[float],
        heading_scores: list[float] | None = None,
        up_scores: list[float] | None = None,
    ) -> None:
        self._ups, self._headings = ups, headings
        self._scores = heading_scores or [0.5] * len(headings)
        self._up_scores = up_scores or [1.0 / (i + 1) for i in range(len(ups))]
        self.levelled: list[np.ndarray] = []

    def ups(self, points: np.ndarray, count: int) -> list[Proposal]:
        return [
            Proposal(u / np.linalg.norm(u), score)
            for u, score in zip(self._ups, self._up_scores, strict=True)
        ][:count]

    def headings(self, levelled: list[np.ndarray], count: int) -> list[list[Proposal]]:
        self.levelled = levelled
        found = list(zip(self._headings, self._scores, strict=True))[:count]
        return [[Proposal(h, score) for h, score in found] for _ in levelled]


def tilted(direction: np.ndarray, degrees: float) -> np.ndarray:
    return axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(degrees)) @ direction


def view(shape: Shape, floor: Floor | None = None) -> np.ndarray:
    """The box chair standing on a Z-up floor, seen from 2 m and 30 degrees up."""
    pose = make_pose(upright_rotation(0.4), np.array([0.0, 0.0, -shape.points[:, 1].min()]))
    camera = camera_at(np.array([0.0, 0.0, 0.4]), 2.0, 30.0, 20.0)
    return render_view(shape, pose, camera, np.random.default_rng(0), floor=floor)


def oriented_by(
    points: np.ndarray,
    up: np.ndarray | None,
    proposer: FixedProposer | None,
    *,
    min_voxels: int = MIN_VOXELS,
    guessed_ups: tuple[SearchedUp, ...] = (),
    **options: float,
) -> Oriented:
    """``orient`` with the engine's counts (8 extractor headings, 3 proposed ups, 2 headings)
    and its ``options`` but those given."""
    return orient(
        points,
        up,
        proposer,
        headings=8,
        voxel=VOXEL,
        min_voxels=min_voxels,
        options=OrientOptions(up_proposals=3, heading_proposals=2, **options),
        guessed_ups=guessed_ups,
    )


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a), -1.0, 1.0))))


def test_a_proposal_a_few_degrees_off_snaps_to_the_seat(box_chair: Shape) -> None:
    points = view(box_chair)
    snapped = snap_to_plane(points, tilted(WORLD_UP, 8.0), voxel=VOXEL)
    assert angle_deg(snapped, WORLD_UP) < 1.5


def test_a_proposal_with_no_plane_near_it_is_kept(box_chair: Shape) -> None:
    points = view(box_chair)
    sideways = tilted(WORLD_UP, 50.0)
    assert np.allclose(snap_to_plane(points, sideways, voxel=VOXEL), sideways)


def test_a_proposal_no_plane_confirms_is_searched_as_a_rough_up(box_chair: Shape) -> None:
    """The seat confirms a proposal 8 degrees off (snapped), none is near one 50 degrees off:
    that one is kept as proposed and marked rough, also on a second look at the cloud."""
    points = view(box_chair)
    proposer = FixedProposer([tilted(WORLD_UP, 8.0), tilted(WORLD_UP, 50.0)], headings=[0.3])
    oriented = oriented_by(points, None, proposer)
    snapped, sideways = oriented.orientations
    assert angle_deg(snapped.up, WORLD_UP) < 1.5 and not snapped.up_rough
    assert angle_deg(sideways.up, WORLD_UP) == pytest.approx(50.0) and sideways.up_rough
    other = FixedProposer([WORLD_UP], headings=[0.3])  # a second look asks it for no up
    again = oriented_by(points, None, other, guessed_ups=oriented.guessed_ups)
    assert [o.up_rough for o in again.orientations] == [False, True]


def test_a_given_up_is_kept_and_its_floor_set_aside(box_chair: Shape) -> None:
    points = view(box_chair, Floor())
    oriented = oriented_by(points, WORLD_UP * 3, None)
    [orientation] = oriented.orientations
    assert orientation.given and np.allclose(orientation.up, WORLD_UP)
    assert orientation.headings == even_headings(8)  # no proposer: every heading
    floor_heights = points[oriented.floor, 2]
    assert oriented.floor.sum() > 0.3 * len(points)
    assert np.abs(floor_heights).max() < 0.05
    assert (points[~oriented.floor, 2] > 0.01).mean() > 0.97


def test_without_up_the_floor_under_a_proposal_becomes_the_first_up(box_chair: Shape) -> None:
    points = view(box_chair, Floor())
    sideways, off = tilted(WORLD_UP, 90.0), tilted(WORLD_UP, 9.0)
    proposer = FixedProposer([sideways, off], headings=[0.3, 2.0, 4.0])
    oriented = oriented_by(points, None, proposer)
    first, second = oriented.orientations
    assert not first.given and angle_deg(first.up, WORLD_UP) < 1.0
    assert np.allclose(second.up, sideways)
    assert oriented.floor.sum() > 0.3 * len(points)
    # headings are proposed on the levelled cloud less its floor, two per up
    assert first.headings == (0.3, 2.0) and first.headings_proposed
    assert all(len(cloud) == (~oriented.floor).sum() for cloud in proposer.levelled)


def test_without_up_a_chair_back_at_the_bottom_of_an_unlikely_proposal_is_no_floor(
    box_chair: Shape,
) -> None:
    # Seen from behind, with up guessed along the chair's front, the backrest is the cloud's
    # bottom, large and flat: a floor by every rule but its spread past the rest of the chair,
    # which the second proposal's floor needs twice over.
    pose = make_pose(upright_rotation(0.4), np.array([0.0, 0.0, -box_chair.points[:, 1].min()]))
    camera = camera_at(np.array([0.0, 0.0, 0.4]), 2.0, 30.0, 200.0)
    points = render_view(box_chair, pose, camera, np.random.default_rng(0))
    front = -(pose[:3, :3] @ np.array([0.0, 0.0, 1.0]))  # the backrest is on canonical +Z
    assert floor_mask(points, front, voxel=VOXEL).sum() > 0.3 * len(points)
    proposer = FixedProposer([WORLD_UP, front], headings=[0.3, 2.0])
    oriented = oriented_by(points, None, proposer)
    assert not oriented.floor.any()
    assert [o.floor_level for o in oriented.orientations] == [None, None]
    assert [o.belief for o in oriented.orientations] == [1.0, 0.5]  # the proposals' order
    assert angle_deg(oriented.orientations[0].up, WORLD_UP) < 1.0


@pytest.mark.parametrize(("scores", "first"), [([0.96, 0.03], 1), ([0.6, 0.35], 2)])
def test_a_second_heading_is_described_first_only_while_the_first_is_unsure(
    box_chair: Shape, scores: list[float], first: int
) -> None:
    proposer = FixedProposer([WORLD_UP], headings=[0.3, 2.0], heading_scores=scores)
    oriented = oriented_by(view(box_chair), WORLD_UP, proposer, heading_mass=0.95)
    assert oriented.orientations[0].headings == (0.3, 2.0)  # both proposals, best first
    assert oriented.first == (first,)
    # Every proposal keeps its mass, described first or not: poses are weighed by it.
    [described] = oriented.described_first
    assert described.proposed_headings == ((0.3, scores[0]), (2.0, scores[1]))


def test_a_pose_is_believed_as_much_as_the_proposed_heading_near_it() -> None:
    proposals = ((0.3, 0.6), (np.pi - 0.1, 0.3))
    orientation = Orientation(WORLD_UP, True, (0.3,), True, proposed_headings=proposals)
    assert orientation.heading_belief(0.3 + np.radians(20), 22.5) == 0.6
    # Across the +-pi seam, and nearer the second proposal than the window's edge.
    assert orientation.heading_belief(-np.pi + 0.1, 22.5) == 0.3
    # Far from every proposal: the mass no proposal holds.
    assert orientation.heading_belief(0.3 + np.pi / 2, 22.5) == pytest.approx(0.1)
    # Evenly spaced headings (no proposer) weigh nothing.
    assert Orientation(WORLD_UP, True, (0.0, np.pi)).heading_belief(1.0, 22.5) == 1.0


@pytest.mark.parametrize(
    ("scores", "first"), [([0.7, 0.2, 0.1], (2, 0, 0)), ([0.4, 0.35, 0.25], (2, 2, 0))]
)
def test_without_up_a_further_up_is_searched_first_only_while_the_ones_before_are_unsure(
    box_chair: Shape, scores: list[float], first: tuple[int, ...]
) -> None:
    ups = [WORLD_UP, tilted(WORLD_UP, 100.0), tilted(WORLD_UP, -100.0)]
    proposer = FixedProposer(ups, headings=[0.3, 2.0], up_scores=scores)
    oriented = oriented_by(view(box_chair), None, proposer, up_mass=0.5)
    assert not oriented.floor.any()
    assert [o.belief for o in oriented.orientations] == scores  # every up kept, in order
    assert oriented.first == first
    assert oriented.held_back
    described = oriented.described_first
    assert len(described) == sum(n > 0 for n in first)
    assert all(o.headings == (0.3, 2.0) for o in described)


@pytest.mark.parametrize("heading", [0.0, 1.2, -2.5])
def test_rotations_level_the_up_and_turn_by_the_heading(heading: float) -> None:
    from catalign.frames import MODEL_UP
    from catalign.registration.results import Orientation

    up = np.array([0.2, -0.3, 0.9])
    [rotation] = rotations_of(Orientation(up, False, (heading,), headings_proposed=True))
    assert np.allclose(rotation @ (up / np.linalg.norm(up)), MODEL_UP)
    # a model turned by the heading about its up comes out of the rotation unturned
    levelled_model = rotation @ np.linalg.inv(rotation) @ axis_angle(MODEL_UP, heading)
    unturned = axis_angle(MODEL_UP, -heading) @ levelled_model
    assert np.allclose(unturned, np.eye(3))


@pytest.mark.parametrize("given", [True, False])
def test_a_plane_with_nothing_standing_on_it_is_no_floor(
    panel_with_a_leg: np.ndarray, given: bool
) -> None:
    points = panel_with_a_leg
    assert floor_mask(points, WORLD_UP, voxel=VOXEL).all()  # every floor rule holds
    assert not floor_mask(points, WORLD_UP, voxel=VOXEL, min_standing=50).any()
    proposer = FixedProposer([WORLD_UP, tilted(WORLD_UP, 90.0)], headings=[0.3, 2.0])
    oriented = oriented_by(points, WORLD_UP if given else None, proposer, min_voxels=50)
    assert not oriented.floor.any()
    assert all(len(cloud) == len(points) for cloud in proposer.levelled)


def test_a_given_up_is_snapped_to_the_seat_only_when_asked(box_chair: Shape) -> None:
    points = view(box_chair)
    off = tilted(WORLD_UP, 6.0)  # an imprecise IMU
    [kept] = oriented_by(points, off, None).orientations
    assert angle_deg(kept.up, off) < 1e-6
    [snapped] = oriented_by(points, off, None, up_snap_deg=10.0).orientations
    assert snapped.given and angle_deg(snapped.up, WORLD_UP) < 1.5
