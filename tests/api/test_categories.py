"""Categories through the API: models carry one, listing filters by it, a request may name one.

One real server on a copy of the 3 procedural chairs, with a fourth model uploaded as a table
(a chair's shape: what is checked is that the category decides which models answer, not how
tables look). The SDK, HTTP with each body and gRPC are asked the same questions.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import grpc
import httpx
import pytest
import trimesh

import catalign_client as sdk
from catalign.api import catalign_pb2, catalign_pb2_grpc
from catalign.data.shapes import procedural_shape

if TYPE_CHECKING:
    from tests.api.conftest import Server, View

UP = [0.0, 0.0, 1.0]


@pytest.fixture(scope="module")
def server(serve: Callable, library_dir: Path, tmp_path_factory) -> Iterator[Server]:
    """A server whose library holds 3 chairs and ``table-7``, uploaded with its category."""
    import shutil

    library = tmp_path_factory.mktemp("categories") / "library"
    shutil.copytree(library_dir, library)
    mesh = procedural_shape(7).mesh
    assert mesh is not None
    ply = trimesh.exchange.ply.export_ply(trimesh.Trimesh(mesh.vertices, mesh.faces))
    with serve(library=library, grpc=True, workers=1, warmup=False) as running:
        with httpx.Client(base_url=running.url, timeout=120) as http:
            added = http.post(
                "/models",
                files={"file": ("t.ply", ply)},
                data={"model_id": "table-7", "category": "table"},
            )
            assert added.status_code == 201, added.text
            assert added.json()["category"] == "table"
        yield running


@pytest.fixture(scope="module")
def view(views: Callable[..., View]) -> View:
    return views(seed=1)  # a view of proc-0001, a chair


def test_models_are_listed_with_their_category_and_filtered_by_it(server: Server) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as http:
        every = http.get("/models").json()
        tables = http.get("/models", params={"category": "table"}).json()
        none = http.get("/models", params={"category": "sofa"}).json()
        bad = http.get("/models", params={"category": "Big Table"})
        one = http.get("/models/table-7").json()
    assert every["categories"] == {"chair": 3, "table": 1}
    assert {m["model_id"]: m["category"] for m in every["models"]}["proc-0001"] == "chair"
    assert [m["model_id"] for m in tables["models"]] == ["table-7"] and tables["count"] == 1
    assert none["count"] == 0 and none["categories"] == every["categories"]
    assert bad.status_code == 422 and "not a valid category" in bad.json()["error"]["message"]
    assert one["category"] == "table"


def test_an_upload_with_a_bad_category_is_refused_and_changes_nothing(
    server: Server, library_dir: Path
) -> None:
    mesh = procedural_shape(8).mesh
    assert mesh is not None
    ply = trimesh.exchange.ply.export_ply(trimesh.Trimesh(mesh.vertices, mesh.faces))
    with httpx.Client(base_url=server.url, timeout=60) as http:
        refused = http.post("/models", files={"file": ("c.ply", ply)}, data={"category": "Tables!"})
        after = http.get("/models").json()
    assert refused.status_code == 422
    assert "not a valid category" in refused.json()["error"]["message"]
    assert after["count"] == 4


def test_a_request_naming_a_category_is_answered_from_it_alone(server: Server, view: View) -> None:
    body = {"points": view.points.tolist(), "up": UP, "seed": 0}
    with httpx.Client(base_url=server.url, timeout=120) as http:
        anything = http.post("/register", json=body).json()
        table = http.post("/register", json=body | {"category": "table"}).json()
        binary = http.post(
            "/register",
            content=view.points.tobytes(),
            headers={"Content-Type": "application/octet-stream"},
            params={"up": "0,0,1", "category": "table"},
        ).json()
    assert (anything["model_id"], anything["category"]) == ("proc-0001", "chair")
    assert (table["model_id"], table["category"]) == ("table-7", "table")
    assert table["category_confidence"] == 1.0  # nothing of another category was searched
    assert 0.0 < anything["category_confidence"] <= 1.0
    assert [c["model_id"] for c in table["candidates"]] == ["table-7"]
    assert all(a["model_id"] == "table-7" for a in table["alternatives"])
    assert (binary["model_id"], binary["category"]) == ("table-7", "table")


def test_an_unknown_category_is_a_422_that_lists_the_librarys(server: Server, view: View) -> None:
    body = {"points": view.points[::4].tolist(), "category": "sofa"}
    with httpx.Client(base_url=server.url, timeout=60) as http:
        unknown = http.post("/register", json=body)
        malformed = http.post("/register", json=body | {"category": "So Fa"})
        typed = http.post("/register", json=body | {"category": 3})
    assert unknown.status_code == 422
    message = unknown.json()["error"]["message"]
    assert "'sofa'" in message and "chair (3), table (1)" in message
    assert malformed.status_code == 422 and typed.status_code == 422


def test_the_sdk_sends_the_category_and_reads_the_answers(server: Server, view: View) -> None:
    with sdk.Client(server.url, timeout=120) as client:
        result = client.align(view.points, up=UP, seed=0, category="table")
        tables = client.models(category="table")
        with pytest.raises(sdk.InvalidInputError, match="chair \\(3\\), table \\(1\\)"):
            client.align(view.points[::4], category="sofa")
    assert (result.model_id, result.category) == ("table-7", "table")
    assert result.to_dict()["category"] == "table" and result.category_confidence == 1.0
    assert [(m.model_id, m.category) for m in tables] == [("table-7", "table")]


def test_grpc_takes_the_category_and_answers_with_it(server: Server, view: View) -> None:
    assert server.grpc_target is not None
    request = {"points": view.points.tobytes(), "up": UP, "seed": 0}
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = catalign_pb2_grpc.CatalignStub(channel)
        table = stub.Register(catalign_pb2.RegisterRequest(**request, category="table"))
        anything = stub.Register(catalign_pb2.RegisterRequest(**request))
        listed = stub.ListModels(catalign_pb2.ListModelsRequest())
        with pytest.raises(grpc.RpcError) as refused:
            stub.Register(catalign_pb2.RegisterRequest(**request, category="sofa"))
    assert (table.model_id, table.category) == ("table-7", "table")
    assert table.category_confidence == 1.0 and table.HasField("category_confidence")
    assert (anything.model_id, anything.category) == ("proc-0001", "chair")
    assert {m.model_id: m.category for m in listed.models}["table-7"] == "table"
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "chair (3), table (1)" in refused.value.details()
