"""The test protocol: test cases built from a seed, the library of each setting, and the loop.

Settings, as in the paper:

* **same**: the library holds the validation shapes, so the observed instance's CAD is in it;
* **cross**: the library holds the training shapes, so the observed instance is never in it.

Every validation shape is observed ``views`` times: upright (or free SO(3)) at a random place,
scaled to a realistic height, seen by a random camera with structured-light noise, capped at
``max_points``. With ``floor`` every view also keeps a ring of floor around the chair, as a
segmentation that kept some floor would; the chair then stands upright on it, and in ``so3``
mode the whole scene is turned at random (a sensor that knows no up). Everything derives from
``seed``, so two runs see the same cases.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from tqdm import tqdm

from catalign.data.shapes import Shape, SharedChairs, to_metric
from catalign.data.views import Floor, PoseMode, random_camera, random_object_pose, render_view
from catalign.errors import DegenerateInputError, InvalidInputError
from catalign.frames import MODEL_UP
from catalign.geometry.ncc import NCCFrame
from catalign.geometry.sampling import subsample
from catalign.geometry.se3 import make_pose, random_rotation, transform
from catalign.registration.base import LibraryShape, Registrar, RegistrationResult

Setting = Literal["same", "cross"]
SETTINGS: tuple[Setting, ...] = ("same", "cross")


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


def metric_shapes(chairs: SharedChairs, ids: Sequence[str]) -> dict[str, Shape]:
    return {i: to_metric(chairs.load(i)) for i in ids}


def build_cases(
    shapes: dict[str, Shape],
    views: int,
    seed: int,
    pose_mode: PoseMode = "upright",
    max_points: int = 20_000,
    floor: bool = False,
) -> list[TestCase]:
    """``views`` noisy partial observations of every shape, all derived from ``seed``.

    ``floor`` keeps a ring of floor (:class:`~catalign.data.views.Floor`, default margin) in
    every view. A chair stands upright on it; in ``so3`` mode the view, floor and all, is then
    turned by a random rotation, so its points before the turn are the ``upright`` floor view's.
    """
    floor_kept = Floor() if floor else None
    turned = floor and pose_mode == "so3"  # a chair on a floor stands on it; the view turns
    placed: PoseMode = "upright" if turned else pose_mode
    cases = []
    for index, (shape_id, shape) in enumerate(sorted(shapes.items())):
        for view in range(views):
            rng = np.random.default_rng([seed, index, view])
            pose = random_object_pose(rng, placed, height=shape.height / 2)
            camera = random_camera(pose[:3, 3], rng)
            seen = render_view(shape, pose, camera, rng, floor=floor_kept)
            points, eye = subsample(seen, max_points, rng), camera.eye
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
) -> list[CaseOutcome]:
    """Prepare ``registrar`` with ``library`` and register every case, timing each query."""
    registrar.prepare([LibraryShape(i, s.points) for i, s in sorted(library.items())])
    outcomes = []
    for case in tqdm(cases, desc=f"{registrar.name} {label}".strip(), unit="case"):
        started = time.perf_counter()
        try:
            result, refused = registrar.register(case.points, seed=seed), None
        except (DegenerateInputError, InvalidInputError) as error:
            result, refused = None, str(error)
        outcomes.append(CaseOutcome(case, result, time.perf_counter() - started, refused))
    return outcomes


def frames_of(shapes: dict[str, Shape]) -> dict[str, NCCFrame]:
    return {i: NCCFrame.fit(s.points) for i, s in shapes.items()}
