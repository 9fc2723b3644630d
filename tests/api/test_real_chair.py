"""A view of a real shared chair, registered through a real server and the real SDK, lands
within the evaluation's thresholds (10 degrees, 5 cm) on a library built from shared chairs."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from catalign.data.shapes import SharedChairs
from catalign.evaluation.metrics import canonical_pose_error
from catalign.evaluation.protocol import build_cases, metric_shapes
from catalign.features.extractor import LearnedExtractor
from catalign.geometry.ncc import NCCFrame
from catalign.library.index import build
from catalign_client import Client

# The first three validation chairs; their views with seed 0 are cases of `catalign evaluate`.
CHAIRS = 3


@pytest.fixture(scope="module")
def real_library(
    shared_chairs: SharedChairs, model_dir: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, dict]:
    shapes = metric_shapes(shared_chairs, shared_chairs.ids("val")[:CHAIRS])
    sources = tmp_path_factory.mktemp("real") / "sources"
    sources.mkdir()
    for shape_id, shape in shapes.items():
        np.save(sources / f"{shape_id}.npy", shape.points.astype(np.float32))
    out = sources.parent / "library"
    build([sources], out, LearnedExtractor(model_dir), progress=False)
    return out, shapes


def test_a_real_chair_view_is_aligned_through_the_sdk(
    real_library: tuple[Path, dict], serve: Callable
) -> None:
    library, shapes = real_library
    cases = build_cases(shapes, views=1, seed=0)
    with serve(library=library, warmup=False) as server, Client(server.url, timeout=120) as client:
        aligned = []
        for case in cases:
            result = client.align(case.points, up=[0, 0, 1], seed=0)
            frame = NCCFrame.fit(shapes[case.shape_id].points)
            error = canonical_pose_error(result.pose, frame, case.pose, frame)
            aligned.append(
                result.model_id == case.shape_id and error.rre_deg < 10.0 and error.rte_m < 0.05
            )
    # measured with the shipped model: all 3 views aligned (the evaluation's "same" rate is
    # near 80%, so one miss is tolerated)
    assert sum(aligned) >= 2, aligned
