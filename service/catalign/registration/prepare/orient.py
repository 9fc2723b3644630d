"""Orienting the query: which ways up it may stand, and at which headings to describe it.

Library models share the category's canonical frame, and the learned features only know
headings within half a bin of it, so the query must be turned towards that frame before it is
described. This stage decides how, from the caller's ``up`` and the orientation proposals of
:mod:`catalign.features.orientation`:

* **with** ``up``: one orientation, levelled by it, described at the ``heading_proposals`` best
  proposed headings (instead of every heading of the extractor);
* **without** ``up``: one orientation per proposed up (``up_proposals``), each levelled by its
  up and described at its own proposed headings; the engine searches under each and keeps the
  best verified pose (with ``up_mass``, under the confident ups first: the others only when
  the answer there is weak);
* with no proposer (FPFH features, a model folder without orientation weights): the caller's
  ``up`` and every heading, or, without ``up``, the free search.

Proposed ups are snapped to the largest plane nearly perpendicular to them
(:func:`snap_to_plane`): a seat or a floor is level to a degree or two, a proposal only to a
few. A proposal with no plane near it is searched as it is, marked rough (:class:`SearchedUp`):
the category fit does not stand another instance on it alone. The **floor** is found here
too, because where the floor is depends on which way is up
(:func:`~catalign.registration.prepare.floor.floor_mask`): under the given up, or under the first
proposed up that has a floor beneath the cloud and spreads past the chair (a chair's back or
side is flat too: ``guessed_floor_spread``), and, given or guessed, that leaves a query's
worth of object standing on it (``min_voxels`` occupied voxels). A floor is the best witness
of up there is, so that proposal's up becomes the floor's normal and is tried first. Its
points are set aside, and its level goes on to the category fit (the chair stands on it).

Every orientation carries the belief in its up: the proposal's probability mass, 1 for a given
up or a floor. The engine weighs verification scores by it, since verification alone too
often prefers an upside-down chair.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from pydantic import Field

from catalign.geometry.levelling import even_headings, leveller
from catalign.geometry.sampling import voxel_downsample
from catalign.options import OptionGroup
from catalign.registration.prepare.floor import DEFAULT_OPTIONS as DEFAULT_FLOOR_OPTIONS
from catalign.registration.prepare.floor import FloorOptions, cone_planes, floor_mask
from catalign.registration.prepare.validation import MIN_VOXELS
from catalign.registration.results import Orientation

if TYPE_CHECKING:  # the proposer is torch's: a query without one imports none
    from catalign.features.orientation import OrientationProposer


class OrientOptions(OptionGroup):
    """How the query is oriented (``engine.orient``): the ways up and headings searched, and
    the planes proposed ups snap to."""

    headings: int | None = Field(default=None, ge=1)
    """Headings the query is described at (None: the extractor's, 8 for ``yaw-bin`` models,
    else 1)."""
    up_proposals: int = Field(default=3, ge=1)
    """Without ``up``: proposed up directions the gravity-aware search runs under (the best
    verified pose wins)."""
    up_mass: float | None = Field(default=0.5, gt=0, le=1)
    """Without ``up``: a further proposed up is searched at first only while the ones before
    it hold less than this probability mass (None: always ``up_proposals``; a floor found under
    the cloud holds it all): a confident up network then costs one up's search instead of
    three; when the answer's confidence is below ``decision.heading_fallback``, the query is
    searched again under every proposed up."""
    up_snap_deg: float | None = Field(default=None, gt=0, le=30)
    """With ``up`` given, snap it to the largest plane within this many degrees of it (a seat,
    the floor), as proposed ups are: for an up known to a few degrees only (an imprecise IMU).
    Off by default: a seat may slope a few degrees, and snapping an exact up to it costs about
    4 of 108 *same* views within 10 degrees; an up 5 or 10 degrees off gains 4 and 17 of them
    (docs/evaluation.md, "An imprecise up")."""
    heading_proposals: int | None = Field(default=2, ge=1)
    """Proposed headings the query is described at, under each up (None: every heading of
    the extractor)."""
    heading_mass: float | None = Field(default=0.95, gt=0, le=1)
    """A further heading proposal is described at first only while the ones before it hold
    less than this probability mass (None: always ``heading_proposals``): a confident heading
    network then costs one heading's features, matching and verification instead of two; when
    the answer's confidence is below ``decision.heading_fallback``, the query is searched again
    at every proposed heading. About 0.85x the time on the evaluation's *same* views and 0.97x
    on *cross* ones, which fall back more often (``docs/benchmarks.md``)."""
    snap_deg: float = Field(default=15.0, gt=0, lt=90)
    """Proposed ups snap to the largest plane within this angle of them (module docstring)."""
    snap_draws: int = Field(default=2048, ge=1)
    """Three-point draws the snapping plane is sought with ..."""
    snap_cell_voxels: float = Field(default=0.8, gt=0)
    """... on a grid of cells this many voxels wide ..."""
    snap_tolerance_voxels: float = Field(default=0.4, gt=0)
    """... with inliers within this share of a voxel ..."""
    snap_share: float = Field(default=0.1, ge=0, le=1)
    """... and a plane must hold this share of the grid's cells ..."""
    snap_min_points: int = Field(default=30, ge=3)
    """... and this many of them at least."""
    guessed_floor_spread: tuple[float, float] = (1.0, 2.0)
    """Under a proposed up, a floor must spread this many times wider than the chair's shadow
    on it (:func:`~catalign.registration.prepare.floor.spread`): under the first proposal,
    then under the less likely others. On the evaluation's so3 views (seeds 0 and 1, no floor)
    a chair's back or side passed every other rule of a floor in 18 of 107 views, 12 of them
    under the second or third proposal, where it spread 0.6 to 1.9 times the rest of the chair.
    A floor disc reaching 0.3 m past the chair, the whole scene turned at random, spread 2.1 to
    11 times in 105 of 106 views (0.55 in the last); a sofa's only 1.75 (1.1 with a disc
    reaching 0.1 m past it)."""


DEFAULT_OPTIONS = OrientOptions()


@dataclass(frozen=True)
class SearchedUp:
    """An up to search under: its ``direction`` (None: a free search), the ``belief`` in it (a
    proposal's probability mass; 1 for a given up or a floor), and whether it is ``rough``: a
    proposed up no plane confirmed, the up network's own direction, good to about ten degrees
    and not to the seat's one or two."""

    direction: np.ndarray | None
    belief: float = 1.0
    rough: bool = False


@dataclass(frozen=True)
class Oriented:
    """The orientations to search, best first, the mask of the points that are floor, and how
    many of each orientation's headings to describe first (the confident ones, none under an
    up held back; the rest only when the answer found at those is weak). ``guessed_ups`` are
    the proposed ups snapped to planes, with their beliefs, before a floor found under one of
    them goes first (empty when ``up`` was given): a second look at the same cloud reuses
    them."""

    orientations: list[Orientation]
    floor: np.ndarray
    first: tuple[int, ...]
    guessed_ups: tuple[SearchedUp, ...] = ()

    @property
    def described_first(self) -> list[Orientation]:
        """The orientations described first, at the headings described first."""
        pairs = zip(self.orientations, self.first, strict=True)
        return [replace(o, headings=o.headings[:n]) for o, n in pairs if n]

    @property
    def held_back(self) -> bool:
        """Whether some orientation has headings that are not among the first described."""
        return any(n < len(o.headings) for o, n in zip(self.orientations, self.first, strict=True))


def orient(
    points: np.ndarray,
    up: np.ndarray | None,
    proposer: OrientationProposer | None,
    *,
    headings: int,
    voxel: float,
    min_voxels: int = MIN_VOXELS,
    options: OrientOptions = DEFAULT_OPTIONS,
    floor_options: FloorOptions = DEFAULT_FLOOR_OPTIONS,
    guessed_ups: tuple[SearchedUp, ...] = (),
) -> Oriented:
    """The orientations to search for ``points`` (module docstring). ``headings`` is what the
    extractor needs without proposals (1 for rotation-invariant features: then no heading is
    proposed); ``options.heading_proposals`` None describes every heading even with a
    proposer, and with ``heading_mass`` a further proposal is among the first described only
    while the ones before it hold less than that probability mass; ``up_mass`` does the same
    for proposed ups (the others are described at no heading first). ``guessed_ups`` (an
    earlier :class:`Oriented`'s) stand for the proposer's ups and make this a second look,
    which seeks no floor: the engine's, when a guessed floor may be a chair's back.
    ``up_snap_deg`` snaps a given ``up`` as a proposed one is, to a plane within that many
    degrees (an up known to a few degrees only: an imprecise IMU)."""
    o = options
    given = up is not None
    second_look = bool(guessed_ups)
    if given:
        direction = leveller(up)[1]  # checked, and of unit length
        if o.up_snap_deg is not None:
            snap = o.model_copy(update={"snap_deg": o.up_snap_deg})
            direction = snap_to_plane(points, direction, voxel=voxel, options=snap)
        ups = [SearchedUp(direction)]
    elif proposer is not None:
        if not guessed_ups:
            proposals = proposer.ups(points, o.up_proposals)
            cells = plane_cells(points, voxel, o)  # laid once for every proposal
            guessed_ups = tuple(_snapped(cells, p.value, p.score, voxel, o) for p in proposals)
        ups = list(guessed_ups)
    else:
        ups = [SearchedUp(None)]

    floor = np.zeros(len(points), dtype=bool)
    for index, candidate in enumerate([] if second_look else ups):
        if candidate.direction is None:
            continue
        floor = floor_mask(
            points,
            candidate.direction,
            voxel=voxel,
            min_spread=0.0 if given else o.guessed_floor_spread[min(index, 1)],
            min_standing=min_voxels,
            options=floor_options,
        )
        if floor.any():
            if not given:  # the floor's normal is the best up there is: tried first
                del ups[index]
                ups.insert(0, SearchedUp(_plane_normal(points[floor], candidate.direction)))
            break
    kept = points[~floor]

    first_up = ups[0].direction
    levels = [float(np.median(points[floor] @ first_up)) if floor.any() else None]
    levels += [None] * (len(ups) - 1)  # the floor lies under the first up only
    propose = first_up is not None and headings > 1 and o.heading_proposals is not None
    if propose and proposer is not None:
        levelled = [kept @ leveller(u.direction).T for u in ups]
        proposed = [
            tuple((float(p.value), p.score) for p in found)
            for found in proposer.headings(levelled, o.heading_proposals)
        ]
        first = tuple(_leading([s for _, s in found], o.heading_mass) for found in proposed)
    else:
        proposed = [()] * len(ups)
        first = (len(even_headings(headings)),) * len(ups)
    orientations = [
        Orientation(
            u.direction,
            given,
            tuple(value for value, _ in found) if found else even_headings(headings),
            bool(found),
            u.belief,
            level,
            found,
            up_rough=u.rough,
        )
        for u, found, level in zip(ups, proposed, levels, strict=True)
    ]
    if not given and proposer is not None:
        searched = _leading([u.belief for u in ups], o.up_mass)
        first = tuple(n if i < searched else 0 for i, n in enumerate(first))
    return Oriented(orientations, floor, first, guessed_ups)


def _snapped(
    cells: np.ndarray, proposed: np.ndarray, belief: float, voxel: float, options: OrientOptions
) -> SearchedUp:
    """A proposed up snapped to the plane near it among the :func:`plane_cells` ``cells``
    (:func:`plane_near`), rough where none is."""
    normal = _plane_among(cells, proposed, voxel=voxel, options=options)
    return SearchedUp(proposed if normal is None else normal, belief, normal is None)


def _leading(beliefs: list[float], mass: float | None) -> int:
    """How many of the leading proposals (their ``beliefs``, best first) come before the
    first whose predecessors hold ``mass`` (all of them when None)."""
    if mass is None:
        return len(beliefs)
    held = np.cumsum([0.0, *beliefs[:-1]])
    return int(np.sum(held < mass))


def snap_to_plane(
    points: np.ndarray, up: np.ndarray, *, voxel: float, options: OrientOptions = DEFAULT_OPTIONS
) -> np.ndarray:
    """``up`` turned onto the normal of the largest plane of ``points`` within ``snap_deg`` of
    it (a seat, a floor, the tops of arms), or left as it is when no such plane holds
    ``snap_share`` of the cloud. A proposal is a few degrees off, a seat or a
    floor is level to a degree or two: on the evaluation's so3 views (seed 0) the share of top
    proposals within 5 degrees of the truth went from 48 to 70 %."""
    normal = plane_near(points, up, voxel=voxel, options=options)
    return up if normal is None else normal


def plane_near(
    points: np.ndarray, up: np.ndarray, *, voxel: float, options: OrientOptions = DEFAULT_OPTIONS
) -> np.ndarray | None:
    """The unit normal (on ``up``'s side) of the largest plane of ``points`` within
    ``snap_deg`` of ``up`` that holds ``snap_share`` of the cloud, None when there is none."""
    cells = plane_cells(points, voxel, options)
    return _plane_among(cells, up, voxel=voxel, options=options)


def plane_cells(points: np.ndarray, voxel: float, options: OrientOptions) -> np.ndarray:
    """The grid planes are sought on: one centroid per cell of ``snap_cell_voxels``."""
    return voxel_downsample(points, options.snap_cell_voxels * voxel)[0]


def _plane_among(
    cloud: np.ndarray, up: np.ndarray, *, voxel: float, options: OrientOptions
) -> np.ndarray | None:
    """:func:`plane_near` on the :func:`plane_cells` ``cloud``."""
    if len(cloud) < 3:
        return None
    o, rng = options, np.random.default_rng(0)
    normals, offsets = cone_planes(cloud, up, max_tilt_deg=o.snap_deg, draws=o.snap_draws, rng=rng)
    if len(normals) == 0:
        return None
    inliers = np.abs(cloud @ normals.T - offsets) < o.snap_tolerance_voxels * voxel
    best = int(np.argmax(inliers.sum(axis=0)))
    if inliers[:, best].sum() < max(o.snap_min_points, o.snap_share * len(cloud)):
        return None
    normal = _plane_normal(cloud[inliers[:, best]], up)
    return normal if normal @ up >= np.cos(np.radians(o.snap_deg)) else None


def _plane_normal(points: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """The unit normal of the plane through ``points`` (least squares), on ``towards``' side."""
    _, _, axes = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    normal = axes[-1]
    return normal if normal @ towards >= 0 else -normal
