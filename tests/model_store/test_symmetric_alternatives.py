"""A seat that looks the same from the front and the back (a bench: a seat slab on four legs
over a rectangular footprint) has two right poses a half turn apart. Its library entry knows
it (symmetry of order 2, found from its surface); the answer returns one pose with that
symmetry, so that a robot knows the other is as right, and never lists the half turn again
among its alternatives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from catalign.data.camera import camera_at
from catalign.data.shapes import Shape, procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor
from catalign.geometry.se3 import make_pose, rotation_error_deg
from catalign.geometry.symmetry import YawSymmetry
from catalign.library.index import build
from catalign.library.loaded import load
from catalign.registration.decision.confidence import find_calibrator
from catalign.registration.engine import Engine

UP = np.array([0.0, 0.0, 1.0])
# Seat 0.6 x 0.4 m at 0.45 m on four 4 cm legs; model frame +Y up, as the library's chairs.
BOXES = [
    ((-0.3, 0.42, -0.2), (0.3, 0.47, 0.2)),
    *[
        ((x - 0.02, 0.0, z - 0.02), (x + 0.02, 0.42, z + 0.02))
        for x in (-0.27, 0.27)
        for z in (-0.17, 0.17)
    ],
]


def _box_surface(low: np.ndarray, high: np.ndarray, count: int, rng: np.random.Generator):
    """``count`` points uniform on the surface of an axis-aligned box."""
    size = high - low
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]]).repeat(2)
    faces = rng.choice(6, size=count, p=areas / areas.sum())
    points = low + rng.random((count, 3)) * size
    axis, side = faces // 2, faces % 2
    points[np.arange(count), axis] = np.where(side == 1, high[axis], low[axis])
    return points


def bench() -> Shape:
    rng = np.random.default_rng(0)
    boxes = [(np.array(lo), np.array(hi)) for lo, hi in BOXES]
    areas = np.array([2 * (np.prod(hi - lo) / (hi - lo)).sum() for lo, hi in boxes])
    counts = np.maximum(200, (15_000 * areas / areas.sum()).astype(int))
    points = np.concatenate(
        [_box_surface(lo, hi, n, rng) for (lo, hi), n in zip(boxes, counts, strict=True)]
    )
    return Shape("bench", points)


@pytest.fixture(scope="module")
def engine(tmp_path_factory: pytest.TempPathFactory) -> Engine:
    if not (DEFAULT_MODEL_DIR / "model.safetensors").is_file():
        pytest.skip("model_store/ has no trained weights")
    extractor = LearnedExtractor()
    if find_calibrator(extractor.model_dir) is None:
        pytest.skip("model_store/ ships no confidence calibrator")
    sources = tmp_path_factory.mktemp("bench") / "sources"
    sources.mkdir()
    for shape in (bench(), procedural_shape(0), procedural_shape(1)):
        np.save(sources / f"{shape.shape_id}.npy", shape.points.astype(np.float32))
    out = Path(sources.parent) / "library"
    build([sources], out, extractor, progress=False)
    return Engine(extractor, load(out, extractor.fingerprint))


@pytest.mark.slow
@pytest.mark.parametrize("yaw", [0.4, 2.2])
def test_a_bench_is_answered_once_with_its_symmetry(engine: Engine, yaw: float):
    shape = bench()
    pose = make_pose(upright_rotation(yaw), np.array([0.5, 0.2, 0.0]))
    camera = camera_at(np.array([0.5, 0.2, 0.3]), 1.8, 35.0, 20.0)
    points = render_view(shape, pose, camera, np.random.default_rng(1))
    answer = engine.register(points, up=UP, seed=0)

    assert answer.model_id == "bench"
    assert answer.symmetry == YawSymmetry(2)
    # Right to the nearest equivalent pose, though perhaps a half turn from the one rendered.
    assert answer.symmetry.rotation_error_deg(answer.pose[:3, :3], pose[:3, :3]) < 10.0
    # Its half turn is the same answer, so no alternative repeats it.
    for other in answer.alternatives:
        if other.model_id == "bench":
            turn = rotation_error_deg(other.pose[:3, :3], answer.pose[:3, :3])
            assert abs(turn - 180.0) > 30.0, f"the half turn is listed again ({turn:.0f} deg)"
