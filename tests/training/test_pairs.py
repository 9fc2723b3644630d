"""Training pairs: positives really correspond, in the right frame, for both pair kinds."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.data.shapes import Shape, procedural_shape
from catalign.training.pairs import (
    MODEL_UP,
    YAW_BINS,
    PairSampler,
    augmentation_rotation,
    positive_pairs,
    voxel_cloud,
)


@pytest.fixture(scope="module")
def sampler() -> PairSampler:
    shapes = {s.shape_id: s for s in (procedural_shape(seed) for seed in (2, 3, 11))}
    ids = sorted(shapes)
    neighbours = {i: [j for j in ids if j != i] for i in ids}
    return PairSampler(shapes, neighbours, voxel_size=0.03, max_positives=500)


def test_positive_pairs_are_nearest_and_within_tau() -> None:
    a = np.array([[0.0, 0, 0], [1, 0, 0], [5, 5, 5]])
    b = np.array([[0.01, 0, 0], [1.2, 0, 0], [0.9, 0, 0]])
    pairs = positive_pairs(a, b, tau=0.15, limit=10, rng=np.random.default_rng(0))
    assert pairs.tolist() == [[0, 0], [1, 2]]


def test_positive_pairs_respect_the_limit() -> None:
    grid = np.random.default_rng(0).random((200, 3))
    pairs = positive_pairs(grid, grid, tau=0.01, limit=50, rng=np.random.default_rng(1))
    assert len(pairs) == 50
    assert (pairs[:, 0] == pairs[:, 1]).all()


def test_voxel_cloud_averages_aligned_positions_per_voxel() -> None:
    points = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.5, 0.5, 0.5]])
    aligned = np.array([[1.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]])
    cloud = voxel_cloud(points, aligned, voxel_size=0.1)
    assert cloud.coords.tolist() == [[0, 0, 0], [5, 5, 5]]
    assert np.allclose(cloud.aligned[:, 0], [2.0, 7.0])


@pytest.mark.parametrize("mode", ["upright", "so3"])
def test_augmentation_rotations_are_rotations(mode: str) -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        rotation = augmentation_rotation(rng, mode)  # type: ignore[arg-type]
        assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
        assert np.isclose(np.linalg.det(rotation), 1.0)
        if mode == "upright":
            tilt = np.degrees(np.arccos(np.clip((rotation @ MODEL_UP) @ MODEL_UP, -1, 1)))
            assert tilt <= 10.0 + 1e-6


def test_same_instance_positives_coincide_in_the_canonical_frame(sampler: PairSampler) -> None:
    sample = sampler.same_instance("proc-0002", np.random.default_rng(0))
    assert sample.kind == "same"
    assert len(sample.positives) > 50
    gap = np.linalg.norm(
        sample.a.aligned[sample.positives[:, 0]] - sample.b.aligned[sample.positives[:, 1]], axis=1
    )
    assert gap.max() < sampler.tau
    # the aligned frame is the shape's canonical one: view voxels lie on the CAD's surface
    assert np.abs(sample.a.aligned).max() < 1.0
    assert sample.neg_radius == pytest.approx(2 * sampler.tau)


def test_cross_instance_pairs_live_in_ncc(sampler: PairSampler) -> None:
    sample = sampler.cross_instance("proc-0002", np.random.default_rng(1))
    assert sample.kind == "cross"
    for cloud in (sample.a, sample.b):
        extent = np.ptp(cloud.aligned, axis=0)
        assert np.linalg.norm(extent) <= 1.0 + 1e-6  # NCC: unit bounding-box diagonal at most
    gap = np.linalg.norm(
        sample.a.aligned[sample.positives[:, 0]] - sample.b.aligned[sample.positives[:, 1]], axis=1
    )
    assert len(gap) > 20 and gap.max() < sampler.tau_ncc


def test_samples_are_deterministic_given_the_rng(sampler: PairSampler) -> None:
    one = sampler.sample("cross", "proc-0003", np.random.default_rng(5))
    two = sampler.sample("cross", "proc-0003", np.random.default_rng(5))
    assert np.array_equal(one.a.coords, two.a.coords)
    assert np.array_equal(one.positives, two.positives)


@pytest.mark.parametrize("mode", sorted(YAW_BINS))
def test_binned_rotations_keep_the_heading_within_half_a_bin(mode: str) -> None:
    """A binned model only learns headings within half a bin of the canonical one, which is
    why the engine tries a query at ``YAW_BINS[mode]`` headings; all of the bin gets used."""
    rng = np.random.default_rng(1)
    half_bin = 180.0 / YAW_BINS[mode]
    headings = []
    for _ in range(400):
        front = augmentation_rotation(rng, mode) @ np.array([0.0, 0.0, 1.0])  # type: ignore[arg-type]
        headings.append(np.degrees(np.arctan2(front[0], front[2])))
    # the small tilt moves the horizontal heading by a fraction of a degree at most
    assert np.max(np.abs(headings)) <= half_bin + 1.0
    assert np.max(np.abs(headings)) >= 0.9 * half_bin


def _plate() -> Shape:
    """A level plate 0.6 m wide and 4 cm thick: a camera above it sees only its top face."""
    rng = np.random.default_rng(0)
    xz = rng.uniform(-0.3, 0.3, size=(4_000, 2))
    faces = [np.column_stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]]) for y in (0.02, -0.02)]
    return Shape("plate", np.concatenate(faces))


@pytest.mark.parametrize(("share", "from_below"), [(0.0, False), (1.0, True)])
def test_views_of_a_chair_in_any_rotation_see_it_from_below(share: float, from_below: bool) -> None:
    sampler = PairSampler({"plate": _plate()}, {"plate": []}, voxel_size=0.03, view_so3_share=share)
    heights = [  # the seen face's height in the plate's own frame
        sampler.same_instance("plate", np.random.default_rng(seed)).a.aligned[:, 1].mean()
        for seed in range(12)
    ]
    assert (min(heights) < 0) == from_below, heights
