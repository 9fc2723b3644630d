"""The test protocol: test cases built from a seed, the library of each setting, and the loop.

Settings, as in the paper:

* **same**: the library holds the validation shapes, so the observed instance's CAD is in it;
* **cross**: the library holds the training shapes, so the observed instance is never in it.

Every validation shape is observed ``views`` times at a random place, scaled to a realistic
height, seen by a random camera with structured-light noise, capped at ``max_points``, in one
of three view modes (:data:`VIEW_MODES`):

* ``upright``: the chair stands with a random yaw, world +Z up;
* ``so3``: the chair in any rotation, so the camera may see it from below (a chair knocked
  over, or on a shelf above the sensor);
* ``turned``: the ``upright`` view, then the whole view turned by a random rotation: a sensor
  without an IMU, held at any angle, looking at a standing chair.

With ``floor`` every view also keeps a ring of floor around the chair, as a segmentation that
kept some floor would; with ``table`` the chair is pushed under a table, whose top hides what
lies beneath it (:func:`~catalign.data.views.under_table`). Either way the chair stands
upright, so ``so3`` with a floor or a table is ``turned``. Everything derives from ``seed``, so
two runs see the same cases, and a view with a table is its twin without one, less the points
the table hides (when neither is capped at ``max_points``).

Views come from one of two sources (:data:`VIEW_SOURCES`): ``single``, one depth camera's
frame as above, or ``fused``, a reconstruction fused from a camera trajectory around the
standing object and cut out loosely (:func:`~catalign.data.reconstruction.reconstruct`: drift,
holes where no camera looked, some floor in half of them, a bit of a neighbour); a fused object
stands upright, so ``so3`` is ``turned``, and ``floor`` keeps the floor in every cut.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from tqdm import tqdm

from catalign.data.camera import random_camera
from catalign.data.reconstruction import Reconstruction, reconstruct
from catalign.data.shapes import Shape, SharedChairs
from catalign.data.views import Floor, PoseMode, random_object_pose, render_view, under_table
from catalign.errors import ConfigError, DegenerateInputError, InvalidInputError
from catalign.frames import MODEL_UP
from catalign.geometry.ncc import NCCFrame
from catalign.geometry.sampling import subsample
from catalign.geometry.se3 import make_pose, random_rotation, transform
from catalign.geometry.symmetry import YawSymmetry, find_yaw_symmetry
from catalign.registration.results import LibraryShape, Registrar, RegistrationResult

Setting = Literal["same", "cross"]
SETTINGS: tuple[Setting, ...] = ("same", "cross")
ViewMode = Literal["upright", "so3", "turned"]
VIEW_MODES: tuple[ViewMode, ...] = ("upright", "so3", "turned")
ViewSource = Literal["single", "fused"]
VIEW_SOURCES: tuple[ViewSource, ...] = ("single", "fused")


@dataclass(frozen=True)
class TestCase:
    """One observation with its ground truth (``pose``: observed shape -> world) and the
    camera's position (``eye``, world)."""

    case_id: str
    shape_id: str
    points: np.ndarray
    pose: np.ndarray
    eye: np.ndarray

    @property
    def elevation_deg(self) -> float:
        """The camera's elevation over the chair's seat plane, in the chair's own frame:
        negative when the camera sees the chair from below."""
        towards = self.pose[:3, :3].T @ (self.eye - self.pose[:3, 3])
        return float(np.degrees(np.arcsin(towards @ MODEL_UP / np.linalg.norm(towards))))


@dataclass(frozen=True)
class CaseOutcome:
    """A case and its answer; ``result`` is None when the method refused the view (too little
    of the chair in sight, too large a cloud), which counts as a failure, with the reason in
    ``refused``."""

    case: TestCase
    result: RegistrationResult | None
    seconds: float
    refused: str | None = None


def metric_shapes(shapes: SharedChairs, ids: Sequence[str]) -> dict[str, Shape]:
    """The shared shapes ``ids``, each scaled to a realistic height of its category."""
    return {i: shapes.metric(i) for i in ids}


def parse_views(text: str) -> tuple[ViewSource, int]:
    """``--views`` as a user writes it: ``single`` or ``fused``, optionally with ``:N`` views
    per shape (2 by default), or a bare ``N`` (N single views)."""
    source, _, count = text.strip().partition(":")
    if source.isdigit() and not count:
        source, count = "single", source
    if source not in VIEW_SOURCES:
        raise ConfigError(
            f"--views {text!r}: expected single, fused, either with :N views per shape "
            "(fused:4), or a number of single views"
        )
    if count and not (count.isdigit() and int(count) >= 1):
        raise ConfigError(f"--views {text!r}: the views per shape must be a whole number >= 1")
    return source, int(count or 2)  # type: ignore[return-value]


def build_cases(
    shapes: dict[str, Shape],
    views: int,
    seed: int,
    pose_mode: ViewMode = "upright",
    max_points: int = 20_000,
    floor: bool = False,
    table: bool = False,
    source: ViewSource = "single",
    reconstruction: Reconstruction | None = None,
) -> list[TestCase]:
    """``views`` noisy partial observations of every shape, all derived from ``seed``.

    A ``turned`` view is the ``upright`` one turned by a random rotation: its points before the
    turn are the ``upright`` view's. ``floor`` keeps a ring of floor
    (:class:`~catalign.data.views.Floor`, default margin) in every view; a chair stands upright
    on it, so an ``so3`` view with a floor is a ``turned`` one; so it does under a ``table``
    (:class:`~catalign.data.views.Table`, drawn at random with a generator of its own).
    ``reconstruction`` sets how fused views are made (default: the simulator's, the floor
    always kept with ``floor``).
    """
    if pose_mode not in VIEW_MODES:
        raise ValueError(f"unknown view mode {pose_mode!r}; expected one of {VIEW_MODES}")
    if source not in VIEW_SOURCES:
        raise ValueError(f"unknown view source {source!r}; expected one of {VIEW_SOURCES}")
    fused = source == "fused"
    if reconstruction is None:
        reconstruction = Reconstruction(floor_kept=1.0) if floor else Reconstruction()
    floor_kept = Floor() if floor else None
    standing = floor or table or fused
    turned = pose_mode == "turned" or (standing and pose_mode == "so3")
    placed: PoseMode = "upright" if turned else pose_mode
    cases = []
    for index, (shape_id, shape) in enumerate(sorted(shapes.items())):
        for view in range(views):
            rng = np.random.default_rng([seed, index, view])
            pose = random_object_pose(rng, placed, height=shape.height / 2)
            if fused:
                made = reconstruct(shape, pose, rng, reconstruction)
                seen, eye = made.points, made.eyes[0]
            else:
                camera = random_camera(pose[:3, 3], rng)
                seen, eye = render_view(shape, pose, camera, rng, floor=floor_kept), camera.eye
            if table:
                hidden = under_table(
                    seen, pose[:3, 3], np.random.default_rng([seed, index, view, 1])
                )
                seen = seen[~hidden]
            points = subsample(seen, max_points, rng)
            if turned:
                turn = make_pose(random_rotation(rng), np.zeros(3))
                points, pose, eye = transform(points, turn), turn @ pose, turn[:3, :3] @ eye
            cases.append(TestCase(f"{shape_id}/{view}", shape_id, points, pose, eye))
    return cases


def run_cases(
    registrar: Registrar,
    library: dict[str, Shape],
    cases: Sequence[TestCase],
    seed: int,
    label: str = "",
    category: str = "chair",
) -> list[CaseOutcome]:
    """Prepare ``registrar`` with ``library`` (shapes of ``category``) and register every case
    naming that category, as a robot whose detector labels the object would; time each."""
    shapes = sorted(library.items())
    registrar.prepare([LibraryShape(i, s.points, s.mesh, category) for i, s in shapes])
    outcomes = []
    for case in tqdm(cases, desc=f"{registrar.name} {label}".strip(), unit="case"):
        started = time.perf_counter()
        try:
            result = registrar.register(case.points, seed=seed, category=category)
            refused = None
        except (DegenerateInputError, InvalidInputError) as error:
            result, refused = None, str(error)
        outcomes.append(CaseOutcome(case, result, time.perf_counter() - started, refused))
    return outcomes


def frames_of(shapes: dict[str, Shape]) -> dict[str, NCCFrame]:
    return {i: NCCFrame.fit(s.points) for i, s in shapes.items()}


def symmetries_of(shapes: dict[str, Shape]) -> dict[str, YawSymmetry]:
    """Each shape's symmetry about its up, found from its surface as a library entry's is."""
    return {i: find_yaw_symmetry(s.points) for i, s in shapes.items()}
