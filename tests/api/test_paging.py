"""``GET /models`` by pages (HTTP, gRPC and the SDK's ``models``/``iter_models``), through a real
server on loopback: every model once, in id order, whatever changes between two pages."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import httpx
import pytest
from hypothesis import given
from hypothesis import strategies as st

import catalign_client as sdk
from catalign.api import catalign_pb2, catalign_pb2_grpc
from catalign.api.paging import CURSOR_PATTERN, decode_cursor, encode_cursor, page
from catalign.errors import InvalidInputError
from tests.api.conftest import Server


@pytest.fixture(scope="module")
def server(serve: Callable, library_dir: Path, tmp_path_factory) -> Iterator[Server]:
    import shutil

    library = tmp_path_factory.mktemp("paging") / "library"
    shutil.copytree(library_dir, library)
    with serve(library=library, grpc=True, workers=1, warmup=False) as running:
        yield running


def test_pages_are_slices_of_the_sorted_ids() -> None:
    ids = [f"m{i:03d}" for i in range(10)]
    for limit in (1, 3, 10, 11):
        seen, cursor = [], None
        while True:
            chunk, cursor = page(ids, ids, limit, cursor)
            seen += chunk
            if cursor is None:
                break
        assert seen == ids
    assert decode_cursor(encode_cursor("chair-7")) == "chair-7"
    # A cursor of a model removed since still resumes after where it stood.
    assert page(ids, ids, 2, encode_cursor("m0045"))[0] == ["m005", "m006"]
    for bad in ("", "not base64!", encode_cursor("x")[1:], encode_cursor("xyz") + "A"):
        with pytest.raises(InvalidInputError, match="not one this server gave"):
            decode_cursor(bad)


@given(st.text(alphabet="YWZ0XI6ab_-=+/!", max_size=24) | st.builds(encode_cursor, st.text()))
def test_a_cursor_is_taken_exactly_when_it_has_the_documented_form(cursor: str) -> None:
    """What ``openapi.yaml`` tells clients a cursor looks like is what the server takes: any
    such cursor resumes somewhere (a position among sorted ids), any other is a 422."""
    documented = CURSOR_PATTERN.fullmatch(cursor) is not None
    try:
        decode_cursor(cursor)
    except InvalidInputError:
        assert not documented
    else:
        assert documented


def test_http_pages_cover_the_library_once(server: Server) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as http:
        everything = http.get("/models").json()
        first = http.get("/models", params={"limit": 2}).json()
        second = http.get("/models", params={"limit": 2, "cursor": first["next_cursor"]}).json()
        bad_cursor = http.get("/models", params={"cursor": "garbage"})
        bad_limit = http.get("/models", params={"limit": 0})
    ids = [m["model_id"] for m in everything["models"]]
    assert ids == sorted(ids) and everything["next_cursor"] is None
    assert (first["count"], first["total"]) == (2, everything["total"])
    assert [m["model_id"] for m in first["models"] + second["models"]] == ids
    assert second["next_cursor"] is None and second["categories"] == everything["categories"]
    assert bad_cursor.status_code == 422
    assert "not one this server gave" in bad_cursor.json()["error"]["message"]
    assert bad_limit.status_code == 422


def test_the_sdk_pages_and_a_removal_between_pages_loses_nothing(
    serve: Callable, library_copy: Path
) -> None:
    with serve(library=library_copy, warmup=False) as running, sdk.Client(running.url) as client:
        ids = [m.model_id for m in client.models()]
        assert [m.model_id for m in client.models(page_size=1)] == ids
        pages = client.iter_models(page_size=1)
        seen = [next(pages).model_id]
        client.remove_model(ids[0])  # the model just given goes; the cursor still holds
        seen += [m.model_id for m in pages]
        with pytest.raises(ValueError, match="page_size"):
            client.models(page_size=0)
    assert seen == ids


def test_grpc_lists_models_by_pages(server: Server) -> None:
    assert server.grpc_target is not None
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = catalign_pb2_grpc.CatalignStub(channel)
        everything = stub.ListModels(catalign_pb2.ListModelsRequest())
        first = stub.ListModels(catalign_pb2.ListModelsRequest(page_size=2))
        rest = stub.ListModels(
            catalign_pb2.ListModelsRequest(page_size=2, page_token=first.next_page_token)
        )
        chairs = stub.ListModels(catalign_pb2.ListModelsRequest(category="chair"))
        with pytest.raises(grpc.RpcError) as refused:
            stub.ListModels(catalign_pb2.ListModelsRequest(page_size=10**6))
    ids = [m.model_id for m in everything.models]
    assert everything.next_page_token == "" and everything.total == len(ids)
    assert [m.model_id for m in [*first.models, *rest.models]] == ids
    assert first.next_page_token and rest.next_page_token == ""
    assert chairs.total == sum(m.category == "chair" for m in everything.models)
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
