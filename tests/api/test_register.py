"""Registration through a real server: accuracy, the three encodings, gRPC, load and metrics."""

from __future__ import annotations

import asyncio
import io
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import grpc
import httpx
import numpy as np
import pytest

from catalign.api import catalign_pb2, catalign_pb2_grpc, health_pb2, health_pb2_grpc
from catalign.geometry.se3 import rotation_error_deg
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.engine import STAGES as ENGINE_STAGES

if TYPE_CHECKING:
    from tests.api.conftest import Server, View

STAGES = {"queue", *ENGINE_STAGES, "total"}
BINARY = {"content-type": "application/octet-stream"}
FAST = {"top_k": 1, "seed": 3}
LIBRARY = {"proc-0000", "proc-0001", "proc-0002"}
# (chair seed, yaw, must be exact): one easy view, two views the checkpoints often get wrong.
VIEWS = [
    (2, 2.5, True),
    (1, 0.7, False),
    (1, 4.4, False),
]  # one candidate: enough to compare encodings, and quick


@pytest.fixture(scope="module")
def server(library_dir: Path, serve: Callable) -> Iterator[Server]:
    with serve(library=library_dir, grpc=True, workers=1, queue=1) as running:
        yield running


@pytest.fixture(scope="module")
def client(server: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=120) as http:
        yield http


@pytest.fixture(scope="module")
def view(views: Callable[..., View]) -> View:
    return views(seed=1)


@pytest.fixture(scope="module")
def json_answer(client: httpx.Client, view: View) -> dict:
    response = client.post("/register", json={"points": view.points.tolist(), **FAST})
    assert response.status_code == 200, response.text
    return response.json()


@pytest.mark.parametrize(("seed", "yaw", "exact"), VIEWS)
def test_views_of_a_library_chair_are_registered(
    client: httpx.Client, views: Callable[..., View], seed: int, yaw: float, exact: bool
) -> None:
    """Every answer is a well-formed rigid pose of a library model; ``exact`` views must also be
    the right model within 10 degrees and 5 cm.

    Not every view is exact: the development checkpoints get 2 to 5 of 9 views of these chairs
    (3 chairs x 3 yaws) exact, and miss the others by front/back flips of nearly symmetric
    partial views or by picking another chair (ICP may then even undo the up prior). The exact
    view is one that both checkpoints register exactly.
    """
    view = views(seed=seed, yaw=yaw)
    request_id = f"accuracy-{seed}-{yaw}"
    response = client.post(
        "/register",
        json={"points": view.points.tolist(), "up": [0, 0, 1]},
        headers={"X-Request-ID": request_id},
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["request_id"] == response.headers["x-request-id"] == request_id
    assert body["model_id"] in LIBRARY
    assert {c["model_id"] for c in body["candidates"]} == LIBRARY
    assert set(body["timings_ms"]) == STAGES
    assert 0 < body["inlier_ratio"] <= 1 and body["num_inliers"] > 0
    pose = np.array(body["pose"])
    rotation = pose[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
    assert body["scale"] == pytest.approx(1.0, abs=1e-6)
    if exact:
        assert body["model_id"] == f"proc-{seed:04d}"
        assert rotation_error_deg(rotation, view.pose[:3, :3]) < 10.0
        assert np.linalg.norm(pose[:3, 3] - view.pose[:3, 3]) < 0.05


def test_json_binary_and_file_give_the_same_answer(
    client: httpx.Client, view: View, json_answer: dict
) -> None:
    binary = client.post("/register", content=view.points.tobytes(), params=FAST, headers=BINARY)
    buffer = io.BytesIO()
    np.save(buffer, view.points)
    upload = client.post("/register", files={"file": ("view.npy", buffer.getvalue())}, params=FAST)
    for response in (binary, upload):
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["model_id"] == json_answer["model_id"]
        np.testing.assert_allclose(body["pose"], json_answer["pose"], atol=1e-9)
        assert body["fitness"] == pytest.approx(json_answer["fitness"], abs=1e-12)
    assert "read" in upload.json()["timings_ms"]


def test_grpc_register_equals_http(server: Server, view: View, json_answer: dict) -> None:
    assert server.grpc_target is not None
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = catalign_pb2_grpc.CatalignStub(channel)
        reply = stub.Register(catalign_pb2.RegisterRequest(points=view.points.tobytes(), **FAST))
        listed = stub.ListModels(catalign_pb2.ListModelsRequest())
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest())
        with pytest.raises(grpc.RpcError) as refused:
            stub.Register(catalign_pb2.RegisterRequest(points=b"\0" * 13))
    assert reply.model_id == json_answer["model_id"]
    np.testing.assert_allclose(np.reshape(reply.pose, (4, 4)), json_answer["pose"], atol=1e-9)
    assert reply.num_inliers == json_answer["num_inliers"]
    assert [c.model_id for c in reply.candidates] == [
        c["model_id"] for c in json_answer["candidates"]
    ]
    assert listed.count == 3 and listed.models[0].model_id == "proc-0000"
    assert health.status == health_pb2.HealthCheckResponse.SERVING
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert ("catalign-error-code", "invalid_input") in refused.value.trailing_metadata()


def test_concurrent_requests_get_200_or_503_and_health_stays_live(
    server: Server, views: Callable[..., View]
) -> None:
    body = views(seed=2, step=4).points.tobytes()

    async def burst() -> tuple[list[httpx.Response], float]:
        async with httpx.AsyncClient(base_url=server.url, timeout=120) as http:
            posts = [
                http.post("/register", content=body, params=FAST, headers=BINARY) for _ in range(50)
            ]

            async def live() -> float:
                await asyncio.sleep(0.2)  # while the worker is busy
                started = time.perf_counter()
                assert (await http.get("/health/live")).status_code == 200
                return time.perf_counter() - started

            *answers, live_s = await asyncio.gather(*posts, live())
            return answers, live_s

    answers, live_s = asyncio.run(burst())
    codes = [r.status_code for r in answers]
    assert set(codes) <= {200, 503}, {r.status_code: r.text for r in answers}
    assert 200 in codes and 503 in codes
    busy = next(r for r in answers if r.status_code == 503)
    assert busy.json()["error"]["code"] == "busy"
    assert int(busy.headers["retry-after"]) >= 1
    assert live_s < 1.0


def test_metrics_count_requests_stages_and_queue(client: httpx.Client, json_answer: dict) -> None:
    text = client.get("/metrics").text
    assert 'catalign_http_requests_total{method="POST",route="/register",status="200"}' in text
    assert 'catalign_stage_duration_seconds_count{stage="match_ransac"}' in text
    assert "catalign_inlier_ratio_count" in text
    assert "catalign_queue_depth" in text
    assert 'catalign_grpc_requests_total{code="OK",method="Register"}' in text


def test_info_describes_what_is_served(client: httpx.Client, server: Server) -> None:
    info = client.get("/info").json()
    assert info["library"]["models"] == 3
    assert info["library"]["path"] == str(server.settings.library)
    assert (info["library"]["indexed"], info["library"]["unindexed"]) == (3, 0)  # as built
    # the weights' sha256, then their retrieval encoders' when they have them
    assert info["library"]["fingerprint"].startswith(info["model_card"]["sha256"])
    assert info["headings"] in (1, 8) and info["voxel_size"] > 0
    served = server.settings.engine.model_dump(mode="json")
    served["orient"]["headings"] = info["headings"]  # resolved for the weights
    assert info["engine"] == served
    assert set(info["versions"]) == {"python", "torch", "open3d", "numpy"}
    if server.settings.model_dir.resolve() == DEFAULT_MODEL_DIR.resolve():
        assert info["categories"] == {"table": ["confidence", "orientation"]}
    else:
        assert set(info["categories"]) == {
            f.name for f in (server.settings.model_dir / "categories").glob("*/")
        }


def test_the_answer_reports_the_up_it_used_and_the_floor_it_set_aside(
    client: httpx.Client, views: Callable[..., View]
) -> None:
    """A view with a ring of floor: with ``up`` the answer echoes it (unit length, not
    estimated) and counts the floor in ``points_set_aside``; without ``up`` it reports an
    estimated up near the true one (the floor's normal)."""
    from catalign.data.camera import camera_at
    from catalign.data.shapes import procedural_shape
    from catalign.data.views import Floor, render_view

    view = views(seed=2, yaw=2.5)
    shape = procedural_shape(2)
    camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
    with_floor = render_view(shape, view.pose, camera, np.random.default_rng(2), floor=Floor())
    assert len(with_floor) > len(view.points) + 2000
    given = client.post("/register", json={"points": with_floor.tolist(), "up": [0, 0, 2]})
    assert given.status_code == 200, given.text
    body = given.json()
    assert body["up"] == pytest.approx([0.0, 0.0, 1.0]) and body["up_estimated"] is False
    assert body["points_set_aside"] >= 0.9 * (len(with_floor) - len(view.points))
    estimated = client.post("/register", json={"points": with_floor.tolist()}).json()
    assert estimated["up_estimated"] is True
    assert np.dot(estimated["up"], [0.0, 0.0, 1.0]) > np.cos(np.radians(2.0))
    assert estimated["points_set_aside"] >= 0.9 * (len(with_floor) - len(view.points))
