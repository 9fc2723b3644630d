"""Symmetry through the API: an uploaded rectangular table is found to look the same turned
half way round; GET /models shows it, and an answer for it carries it (HTTP, SDK, gRPC) and
never lists the half turn again among its alternatives.

One real server on a copy of the 3 procedural chairs, with the table uploaded as a mesh.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import grpc
import httpx
import numpy as np
import pytest
import trimesh

import catalign_client as sdk
from catalign.api import catalign_pb2, catalign_pb2_grpc
from catalign.data.camera import camera_at
from catalign.data.shapes import Shape
from catalign.data.views import render_view, upright_rotation
from catalign.geometry.io import MeshData
from catalign.geometry.se3 import make_pose, rotation_error_deg
from catalign.geometry.symmetry import YawSymmetry

if TYPE_CHECKING:
    from tests.api.conftest import Server

UP = [0.0, 0.0, 1.0]
HALF_TURN = {"order": 2, "yaws_deg": [0.0, 180.0]}


def desk() -> trimesh.Trimesh:
    """A 1.2 x 0.7 m top at 0.72 m on four legs, +Y up (the library's frame)."""
    top = trimesh.creation.box((1.2, 0.04, 0.7))
    top.apply_translation((0.0, 0.72, 0.0))
    legs = []
    for x in (-0.55, 0.55):
        for z in (-0.3, 0.3):
            leg = trimesh.creation.box((0.05, 0.7, 0.05))
            leg.apply_translation((x, 0.35, z))
            legs.append(leg)
    return trimesh.util.concatenate([top, *legs])


@pytest.fixture(scope="module")
def server(serve: Callable, library_dir: Path, tmp_path_factory) -> Iterator[Server]:
    import shutil

    library = tmp_path_factory.mktemp("symmetry") / "library"
    shutil.copytree(library_dir, library)
    with serve(library=library, grpc=True, workers=1, warmup=False) as running:
        with httpx.Client(base_url=running.url, timeout=120) as http:
            added = http.post(
                "/models",
                files={"file": ("desk.ply", trimesh.exchange.ply.export_ply(desk()))},
                data={"model_id": "desk", "category": "table"},
            )
            assert added.status_code == 201, added.text
        yield running


@pytest.fixture(scope="module")
def view() -> tuple[np.ndarray, np.ndarray]:
    """Points of the desk standing on the floor (+Z up), seen from one side, and its pose."""
    mesh = desk()
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    points, _ = trimesh.sample.sample_surface(mesh, 15_000, seed=0)
    shape = Shape("desk", np.asarray(points), MeshData(vertices=vertices, faces=faces))
    pose = make_pose(upright_rotation(0.5), np.array([0.4, -0.3, 0.0]))
    camera = camera_at(np.array([0.4, -0.3, 0.4]), 2.2, 30.0, 35.0)
    cloud = render_view(shape, pose, camera, np.random.default_rng(2))
    return np.ascontiguousarray(cloud, dtype=np.float32), pose


def test_the_model_shows_its_symmetry(server: Server) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as http:
        one = http.get("/models/desk").json()
        listed = {m["model_id"]: m["symmetry"] for m in http.get("/models").json()["models"]}
    assert one["symmetry"] == HALF_TURN
    assert listed["desk"] == HALF_TURN
    assert all(listed[i]["order"] >= 0 for i in listed)


def test_the_answer_carries_the_symmetry_and_no_half_turn_alternative(
    server: Server, view: tuple[np.ndarray, np.ndarray]
) -> None:
    points, pose = view
    body = {"points": points.tolist(), "up": UP, "seed": 0, "category": "table"}
    with httpx.Client(base_url=server.url, timeout=120) as http:
        answer = http.post("/register", json=body).json()
    assert answer["model_id"] == "desk" and answer["symmetry"] == HALF_TURN
    found = np.asarray(answer["pose"])[:3, :3]
    assert YawSymmetry(2).rotation_error_deg(found, pose[:3, :3]) < 10.0
    for other in answer["alternatives"]:
        turn = rotation_error_deg(np.asarray(other["pose"])[:3, :3], found)
        assert abs(turn - 180.0) > 30.0, f"the half turn is listed again ({turn:.0f} degrees)"


def test_the_sdk_and_grpc_read_the_symmetry(
    server: Server, view: tuple[np.ndarray, np.ndarray]
) -> None:
    points, _ = view
    with sdk.Client(server.url, timeout=120) as client:
        result = client.align(points, up=UP, seed=0, category="table")
        (model,) = client.models(category="table")
    assert result.symmetry == sdk.Symmetry(order=2, yaws_deg=(0.0, 180.0))
    assert not result.symmetry.continuous and model.symmetry == result.symmetry
    assert result.to_dict()["symmetry"] == HALF_TURN
    assert server.grpc_target is not None
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = catalign_pb2_grpc.CatalignStub(channel)
        reply = stub.Register(
            catalign_pb2.RegisterRequest(points=points.tobytes(), up=UP, seed=0, category="table")
        )
        listed = stub.ListModels(catalign_pb2.ListModelsRequest())
    assert (reply.symmetry.order, list(reply.symmetry.yaws_deg)) == (2, [0.0, 180.0])
    assert {m.model_id: m.symmetry.order for m in listed.models}["desk"] == 2
