"""The real SDK against a real server on loopback: what a robot's code actually does."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

import catalign_client as sdk

if TYPE_CHECKING:
    from tests.api.conftest import Server, View


@pytest.fixture(scope="module")
def server(library_dir: Path, serve: Callable, tmp_path_factory) -> Iterator[Server]:
    import shutil

    library = tmp_path_factory.mktemp("sdk") / "library"
    shutil.copytree(library_dir, library)
    with serve(library=library, workers=1, queue=4) as running:
        yield running


@pytest.fixture(scope="module")
def view(views: Callable[..., View]) -> View:
    return views(seed=2, yaw=2.5)


def test_align_returns_a_typed_result_with_a_numpy_pose(server: Server, view: View) -> None:
    with sdk.Client(server.url, timeout=120) as client:
        result = client.align(view.points, up=(0, 0, 1), seed=3)
    assert isinstance(result, sdk.AlignResult)
    assert result.model_id in {"proc-0000", "proc-0001", "proc-0002"}
    assert result.pose.shape == (4, 4) and result.pose.dtype == np.float64
    assert np.allclose(result.rotation @ result.rotation.T, np.eye(3), atol=1e-6)
    assert 0.0 <= result.inlier_ratio <= 1.0 and result.num_inliers >= 0
    assert result.request_id and "features" in result.timings_ms


def test_binary_and_json_give_the_same_answer(server: Server, view: View) -> None:
    with sdk.Client(server.url, timeout=120) as client:
        binary = client.align(view.points, seed=5, top_k=1)
        as_json = client.align(view.points.tolist(), seed=5, top_k=1, encoding="json")
    assert binary.model_id == as_json.model_id
    np.testing.assert_allclose(binary.pose, as_json.pose, atol=1e-6)


def test_align_file_uploads_and_parses(server: Server, view: View, tmp_path: Path) -> None:
    path = tmp_path / "cloud.npy"
    np.save(path, view.points)
    with sdk.Client(server.url, timeout=120) as client:
        from_file = client.align_file(path, seed=5, top_k=1)
        direct = client.align(view.points, seed=5, top_k=1)
    assert from_file.model_id == direct.model_id
    np.testing.assert_allclose(from_file.pose, direct.pose, atol=1e-6)


def test_models_add_and_remove(server: Server, tmp_path: Path) -> None:
    from catalign.data.shapes import procedural_shape

    path = tmp_path / "visitor.npy"
    np.save(path, procedural_shape(7).points.astype(np.float32))
    with sdk.Client(server.url, timeout=120) as client:
        before = {m.model_id for m in client.models()}
        added = client.add_model(path)
        assert added.model_id == "visitor"
        assert {m.model_id for m in client.models()} == before | {"visitor"}
        with pytest.raises(sdk.ConflictError):
            client.add_model(path)
        assert client.remove_model("visitor") == len(before)
        with pytest.raises(sdk.NotFoundError) as caught:
            client.model("visitor")
        assert caught.value.status_code == 404 and caught.value.code == "model_not_found"


def test_errors_are_typed_and_carry_the_servers_message(server: Server) -> None:
    line = np.c_[np.linspace(0, 3, 400), np.zeros(400), np.zeros(400)]
    with sdk.Client(server.url, timeout=120) as client:
        with pytest.raises(sdk.InvalidInputError) as caught:
            client.align(line)
        assert caught.value.status_code == 422 and "line" in caught.value.message
        with pytest.raises(sdk.InvalidPointsError):
            client.align(np.full((10, 3), np.nan))
        assert client.health() is True


def test_async_client_mirrors_the_sync_one(server: Server, view: View) -> None:
    async def run() -> sdk.AlignResult:
        async with sdk.AsyncClient(server.url, timeout=120) as client:
            return await client.align(view.points, seed=5, top_k=1)

    result = asyncio.run(run())
    with sdk.Client(server.url, timeout=120) as client:
        expected = client.align(view.points, seed=5, top_k=1)
    assert result.model_id == expected.model_id
    np.testing.assert_allclose(result.pose, expected.pose, atol=1e-6)
