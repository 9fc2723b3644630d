"""Requests within the limits that must not crash, hang or 500 the server, each against a live one.

A 59-byte PCD that claims a billion points, a far point, half a million random points, a client
that leaves mid-request, upload folders left behind by a killed server, options sent as strings,
and a 4-point model: each gets a clear answer, and the server stays up and clean.
"""

from __future__ import annotations

import io
import os
import re
import shutil
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import numpy as np
import pytest

from catalign.api.spool import LIBRARY_SPOOL, LOCK_NAME

if TYPE_CHECKING:
    from tests.api.conftest import Server, View

EVIL_PCD = b"VERSION .7\nFIELDS x y z\nPOINTS 1000000000\nDATA ascii\n1 2 3\n"
UP = "0,0,1"


@pytest.fixture(scope="module")
def server(library_dir: Path, serve: Callable, tmp_path_factory: pytest.TempPathFactory):
    library = tmp_path_factory.mktemp("hardening") / "library"
    shutil.copytree(library_dir, library)
    with serve(library=library, warmup=False) as running:
        yield running


@pytest.fixture(scope="module")
def client(server: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=120) as http:
        yield http


def metric(client: httpx.Client, name: str, labels: str = "") -> float:
    """One sample of the server's Prometheus metrics (0 when the series does not exist yet)."""
    pattern = re.compile(rf"^{re.escape(name)}{re.escape(labels)} (\S+)$", re.MULTILINE)
    found = pattern.search(client.get("/metrics").text)
    return float(found.group(1)) if found else 0.0


def binary(points: np.ndarray) -> bytes:
    return np.ascontiguousarray(points, dtype="<f4").tobytes()


@pytest.mark.parametrize("path", ["/register", "/models"])
def test_a_pcd_that_lies_about_its_size_is_refused(client: httpx.Client, path: str) -> None:
    answer = client.post(path, files={"file": ("evil.pcd", EVIL_PCD)})
    assert answer.status_code == 422, answer.text
    message = answer.json()["error"]["message"]
    assert "evil.pcd" in message and "1000000000" in message
    assert client.get("/health/live").status_code == 200


@pytest.mark.parametrize("far", [[30_000.0, 0.0, 0.0], [3.4e38, 3.4e38, -3.4e38]])
def test_one_far_point_is_set_aside_and_counted(
    client: httpx.Client, views: Callable[..., View], far: list[float]
) -> None:
    view = views(1, step=4)
    points = np.r_[view.points, np.asarray([far], dtype=np.float32)]
    answer = client.post("/register", content=binary(points), params={"up": UP}, headers=_BINARY)
    assert answer.status_code == 200, answer.text
    assert answer.json()["points_set_aside"] == 1
    assert answer.json()["model_id"] == "proc-0001"


@pytest.mark.parametrize("up", [UP, None])
def test_a_plane_with_a_few_points_under_it_gets_an_answer_not_a_500(
    client: httpx.Client, panel_with_a_leg: np.ndarray, up: str | None
) -> None:
    """Every rule of a floor holds for the panel, but nothing stands on it: it is no floor,
    and the cloud is registered (a 500 when the whole cloud was set aside as floor)."""
    params = {} if up is None else {"up": up}
    answer = client.post(
        "/register", content=binary(panel_with_a_leg), params=params, headers=_BINARY
    )
    assert answer.status_code in (200, 422), answer.text
    if answer.status_code == 200:
        assert answer.json()["points_set_aside"] < len(panel_with_a_leg) // 2
    else:
        assert "no pose fits" in answer.json()["error"]["message"]


def test_a_volume_of_random_points_is_refused_quickly(client: httpx.Client) -> None:
    """500,000 points in a 2 m cube (6 MB, under max_points): minutes and 10 GB before."""
    cube = np.random.default_rng(0).uniform(0.0, 2.0, size=(500_000, 3))
    started = time.monotonic()
    answer = client.post("/register", content=binary(cube), headers=_BINARY)
    assert answer.status_code == 422, answer.text
    assert "more than a view of one chair" in answer.json()["error"]["message"]
    assert time.monotonic() - started < 10.0


@pytest.mark.parametrize(
    ("options", "field"), [({"seed": "7"}, "seed"), ({"estimate_scale": "yes"}, "estimate_scale")]
)
def test_json_options_are_not_coerced(client: httpx.Client, options: dict, field: str) -> None:
    answer = client.post("/register", json={"points": [[0, 0, 0]] * 60, **options})
    assert answer.status_code == 422
    assert field in answer.json()["error"]["message"]


def test_a_four_point_model_is_refused(client: httpx.Client) -> None:
    ply = b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
    ply += b"property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
    answer = client.post("/models", files={"file": ("tiny.ply", ply)})
    assert answer.status_code == 422, answer.text
    assert "voxels" in answer.json()["error"]["message"]
    assert "tiny" not in {m["model_id"] for m in client.get("/models").json()["models"]}


def test_a_request_past_its_deadline_answers_503_and_frees_its_worker(
    library_dir: Path, serve: Callable, views: Callable[..., View]
) -> None:
    with (
        serve(library=library_dir, warmup=False, deadline_s=0.05) as running,
        httpx.Client(base_url=running.url, timeout=60) as http,
    ):
        answer = http.post(
            "/register", content=binary(views(2).points), params={"up": UP}, headers=_BINARY
        )
        assert answer.status_code == 503, answer.text
        assert answer.json()["error"]["code"] == "deadline_exceeded"
        assert int(answer.headers["retry-after"]) >= 1
        assert metric(http, "catalign_deadline_exceeded_total", '{reason="deadline"}') == 1
        _wait_until(lambda: metric(http, "catalign_jobs_in_flight") == 0)


def test_a_client_that_disconnects_stops_its_registration(
    library_dir: Path, serve: Callable, views: Callable[..., View]
) -> None:
    body = binary(views(2).points)
    with serve(library=library_dir, warmup=False) as running:
        host, port = running.url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port))) as raw:
            raw.sendall(
                b"POST /register?up=0,0,1 HTTP/1.1\r\nHost: x\r\n"
                b"Content-Type: application/octet-stream\r\n"
                + f"Content-Length: {len(body)}\r\n\r\n".encode()
                + body
            )
            time.sleep(0.1)  # the registration is running
        with httpx.Client(base_url=running.url, timeout=60) as http:
            _wait_until(
                lambda: (
                    metric(http, "catalign_deadline_exceeded_total", '{reason="client_gone"}') == 1
                )
            )
            _wait_until(lambda: metric(http, "catalign_jobs_in_flight") == 0)
            assert 'status="499"' in http.get("/metrics").text


def test_stale_upload_folders_are_removed_at_start_up(
    library_copy: Path, serve: Callable, views: Callable[..., View]
) -> None:
    """A killed server leaves its spool folder behind; the next start removes it."""
    stale = library_copy / LIBRARY_SPOOL / "deadhost-4242-abcdef"
    stale.mkdir(parents=True)
    (stale / LOCK_NAME).touch()
    (stale / "upload-x").mkdir()
    (stale / "upload-x" / "cloud.npy").write_bytes(b"\0" * 4096)
    with serve(library=library_copy, warmup=False) as running:
        assert not stale.exists()
        own = [p for p in (library_copy / LIBRARY_SPOOL).iterdir() if not p.name.startswith(".")]
        assert len(own) == 1 and own[0].name.startswith(f"{socket.gethostname()}-{os.getpid()}-")
        buffer = _npy(views(0, step=2).points)
        with httpx.Client(base_url=running.url, timeout=120) as http:
            answer = http.post("/register", files={"file": ("v.npy", buffer)}, params={"up": UP})
        assert answer.status_code == 200, answer.text
        assert list(own[0].iterdir()) == [own[0] / LOCK_NAME]  # the upload's folder is gone
    assert not own[0].exists()


def test_the_api_key_can_come_from_a_file(
    library_dir: Path, serve: Callable, tmp_path: Path
) -> None:
    key_file = tmp_path / "key"
    key_file.write_text("from-a-file-123\n")
    with (
        serve(library=library_dir, warmup=False, api_key_file=key_file) as running,
        httpx.Client(base_url=running.url, timeout=60) as http,
    ):
        assert http.get("/models").status_code == 401
        assert http.get("/models", headers={"X-API-Key": "from-a-file-123"}).status_code == 200


_BINARY = {"content-type": "application/octet-stream"}


def _npy(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points)
    return buffer.getvalue()


def _wait_until(condition: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not true after {timeout:g} s")
        time.sleep(0.05)
