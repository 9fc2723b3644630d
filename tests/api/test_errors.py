"""Every refusal answers the right status and code, with the request id, and never a 500.

One server for the module, started with an API key, read-only, a 256 KiB body limit and a
1,000-point limit, so that every limit is cheap to reach.
"""

from __future__ import annotations

import asyncio
import base64
import http.client
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import grpc
import httpx
import numpy as np
import pytest

from catalign.api import catalign_pb2, catalign_pb2_grpc, health_pb2, health_pb2_grpc
from catalign.api.app import create_app
from catalign.api.deps import get_service
from catalign.api.settings import ServiceSettings

if TYPE_CHECKING:
    from tests.api.conftest import Server

KEY = "test-key-0123456789"
BODY_LIMIT = 256 * 1024
POINT_LIMIT = 1000
JSON = {"content-type": "application/json"}
BINARY = {"content-type": "application/octet-stream"}


@pytest.fixture(scope="module")
def server(library_dir: Path, serve: Callable) -> Iterator[Server]:
    with serve(
        library=library_dir,
        grpc=True,
        api_key=KEY,
        read_only=True,
        max_body_bytes=BODY_LIMIT,
        max_points=POINT_LIMIT,
        warmup=False,
    ) as running:
        yield running


@pytest.fixture(scope="module")
def client(server: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, headers={"X-API-Key": KEY}, timeout=60) as http:
        yield http


def _floats(count: int) -> bytes:
    return np.random.default_rng(0).normal(size=(count, 3)).astype("<f4").tobytes()


CASES = {
    "malformed JSON": ("POST", "/register", {"content": b'{"points": [[0, 0', "headers": JSON}),
    "NaN": (
        "POST",
        "/register",
        {"content": b'{"points": [[NaN, 0, 0], [1, 2, 3]]}', "headers": JSON},
    ),
    "one point": ("POST", "/register", {"json": {"points": [[0.1, 0.2, 0.3]]}}),
    "wrong shape": ("POST", "/register", {"json": {"points": [[1, 2], [3, 4]]}}),
    "not numbers": ("POST", "/register", {"json": {"points": [["a", "b", "c"]]}}),
    "no points": ("POST", "/register", {"json": {"cloud": []}}),
    "bad option": ("POST", "/register", {"json": {"points": [[0, 0, 0]], "top_k": 0}}),
    "bad up": (
        "POST",
        "/register",
        {"content": _floats(100), "params": {"up": "0,0"}, "headers": BINARY},
    ),
    "13 bytes": ("POST", "/register", {"content": b"\0" * 13, "headers": BINARY}),
    "empty body": ("POST", "/register", {"content": b"", "headers": BINARY}),
    "too many points": (
        "POST",
        "/register",
        {"content": _floats(POINT_LIMIT + 1), "headers": BINARY},
    ),
    "too many JSON points": (
        "POST",
        "/register",
        {"json": {"points": [[0.0, 0.0, 0.0]] * (POINT_LIMIT + 1)}},
    ),
    "unreadable file": ("POST", "/register", {"files": {"file": ("v.ply", b"ply\nnonsense\n")}}),
    "unknown suffix": ("POST", "/register", {"files": {"file": ("v.txt", b"1 2 3\n")}}),
    "no file field": ("POST", "/register", {"files": {"other": ("v.npy", b"x")}}),
    "content type": (
        "POST",
        "/register",
        {"content": b"1 2 3", "headers": {"content-type": "text/plain"}},
    ),
    "oversized body": (
        "POST",
        "/register",
        {"content": b"\0" * (BODY_LIMIT + 12), "headers": BINARY},
    ),
    "unknown model": ("GET", "/models/no-such-chair", {}),
    "encoded traversal": ("GET", "/models/..%2F..%2Fetc", {}),
    "read-only add": ("POST", "/models", {"files": {"file": ("c.npy", b"x")}}),
    "read-only remove": ("DELETE", "/models/proc-0000", {}),
    "unknown route": ("GET", "/no/such/route", {}),
    "wrong method": ("PUT", "/models/proc-0000", {}),
    "empty up": (
        "POST",
        "/register",
        {"content": _floats(300), "headers": BINARY, "params": {"up": ""}},
    ),
}
EXPECTED = {
    "malformed JSON": (422, "invalid_input"),
    "deep JSON": (422, "invalid_input"),
    "NaN": (422, "invalid_input"),
    "one point": (422, "degenerate_input"),
    "wrong shape": (422, "invalid_input"),
    "not numbers": (422, "invalid_input"),
    "no points": (422, "invalid_input"),
    "bad option": (422, "invalid_input"),
    "bad up": (422, "invalid_input"),
    "13 bytes": (422, "invalid_input"),
    "empty body": (422, "invalid_input"),
    "too many points": (422, "invalid_input"),
    "too many JSON points": (422, "invalid_input"),
    "unreadable file": (422, "invalid_file"),
    "unknown suffix": (422, "invalid_file"),
    "no file field": (422, "invalid_input"),
    "content type": (415, "unsupported_media_type"),
    "oversized body": (413, "payload_too_large"),
    "unknown model": (404, "model_not_found"),
    "encoded traversal": (422, "invalid_input"),
    "read-only add": (403, "read_only"),
    "read-only remove": (403, "read_only"),
    "unknown route": (404, "not_found"),
    "wrong method": (405, "method_not_allowed"),
    "empty up": (422, "invalid_input"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_refusals_have_the_right_status_and_code(client: httpx.Client, case: str) -> None:
    method, path, kwargs = CASES[case]
    request_id = "case-" + case.replace(" ", "-")
    options = {**kwargs, "headers": {**kwargs.get("headers", {}), "X-Request-ID": request_id}}
    response = client.request(method, path, **options)
    body = response.json()
    assert (response.status_code, body["error"]["code"]) == EXPECTED[case], response.text
    assert body["error"]["message"]
    assert body["request_id"] == response.headers["x-request-id"] == request_id


def test_a_wrong_method_names_every_method_the_path_allows(client: httpx.Client) -> None:
    response = client.put("/models/proc-0000")
    assert response.status_code == 405
    assert response.headers["allow"] == "DELETE, GET"
    assert client.put("/models").headers["allow"] == "GET, POST"
    # /models/{id}/points is also what /models/{id:path} would match, with a slash in the id
    assert client.put("/models/proc-0000/points").headers["allow"] == "GET"
    removal = client.delete("/models/proc-0000/points")  # not a removal of "proc-0000/points"
    assert (removal.status_code, removal.headers["allow"]) == (405, "GET")
    assert client.get("/models/proc-0000").status_code == 200  # the model is still there


def test_an_unknown_model_is_named_without_the_servers_paths(
    client: httpx.Client, server: Server
) -> None:
    message = client.get("/models/no-such-chair").json()["error"]["message"]
    assert "'no-such-chair'" in message
    assert str(server.settings.library) not in message and "/" not in message


def test_the_point_limit_is_named(client: httpx.Client) -> None:
    response = client.post("/register", content=_floats(POINT_LIMIT + 1), headers=BINARY)
    assert str(POINT_LIMIT) in response.json()["error"]["message"]


def test_a_streamed_body_over_the_limit_is_cut_off(client: httpx.Client) -> None:
    def chunks() -> Iterator[bytes]:  # no Content-Length: checked while reading
        for _ in range(5):
            yield b"\0" * (64 * 1024 - 4)

    response = client.post("/register", content=chunks(), headers=BINARY)
    assert response.status_code == 413
    assert response.json()["error"]["code"] == "payload_too_large"


def test_a_raw_traversal_path_is_refused(server: Server) -> None:
    host, port = server.url.removeprefix("http://").split(":")
    connection = http.client.HTTPConnection(host, int(port), timeout=10)
    connection.request("GET", "/models/../x", headers={"X-API-Key": KEY})
    response = connection.getresponse()
    assert response.status == 422
    connection.close()


@pytest.mark.parametrize("key", [None, "wrong-key-0123456789"])
@pytest.mark.parametrize("path", ["/models", "/info", "/metrics", "/models/proc-0000"])
def test_a_missing_or_wrong_key_is_refused(server: Server, key: str | None, path: str) -> None:
    headers = {} if key is None else {"X-API-Key": key}
    response = httpx.get(f"{server.url}{path}", headers=headers)
    assert response.status_code == 401
    assert response.json()["error"]["code"] == "unauthorized"


@pytest.mark.parametrize("scheme", ["Bearer", "bearer"])
@pytest.mark.parametrize("path", ["/models", "/metrics"])
def test_the_key_is_accepted_as_a_bearer_token(server: Server, scheme: str, path: str) -> None:
    """What a Prometheus ServiceMonitor's ``authorization`` field sends."""
    response = httpx.get(f"{server.url}{path}", headers={"Authorization": f"{scheme} {KEY}"})
    assert response.status_code == 200


@pytest.mark.parametrize("authorization", ["Bearer wrong-key-99", "Bearer", f"Bearer  {KEY}x"])
def test_a_wrong_bearer_token_is_refused_in_a_sentence(server: Server, authorization: str) -> None:
    response = httpx.get(f"{server.url}/metrics", headers={"Authorization": authorization})
    assert response.status_code == 401
    error = response.json()["error"]
    assert error["code"] == "unauthorized"
    assert error["message"] == "wrong API key in the Authorization header (Bearer)"


@pytest.mark.parametrize(
    "authorization",
    ["Basic " + base64.b64encode(f"prometheus:{KEY}".encode()).decode(), KEY, "Token x"],
)
def test_another_authorization_scheme_is_refused(server: Server, authorization: str) -> None:
    response = httpx.get(f"{server.url}/models", headers={"Authorization": authorization})
    assert response.status_code == 401
    message = response.json()["error"]["message"]
    assert "'Bearer <key>'" in message and "X-API-Key" in message
    assert KEY not in message


def test_a_missing_key_names_both_ways_to_send_it(server: Server) -> None:
    message = httpx.get(f"{server.url}/info").json()["error"]["message"]
    assert "X-API-Key header" in message and "Authorization header" in message


def test_every_key_sent_must_be_right(server: Server) -> None:
    def answer(headers: dict[str, str]) -> tuple[int, str | None]:
        response = httpx.get(f"{server.url}/info", headers=headers)
        return response.status_code, response.json().get("error", {}).get("message")

    bearer, wrong_bearer = f"Bearer {KEY}", "Bearer wrong-key-0123456789"
    assert answer({"X-API-Key": "wrong-key-0123456789", "Authorization": bearer}) == (
        401,
        "wrong API key in the X-API-Key header",
    )
    assert answer({"X-API-Key": KEY, "Authorization": wrong_bearer}) == (
        401,
        "wrong API key in the Authorization header (Bearer)",
    )
    assert answer({"X-API-Key": KEY, "Authorization": bearer})[0] == 200
    for other in ("Basic dXNlcjpwYXNz", ""):  # not a Bearer key, even next to a right one
        status, message = answer({"X-API-Key": KEY, "Authorization": other})
        assert status == 401 and "'Bearer <key>'" in (message or "")


def test_register_needs_the_key_before_anything_else(server: Server) -> None:
    response = httpx.post(f"{server.url}/register", json={"points": [[0, 0, 0]]})
    assert response.status_code == 401


def test_health_stays_open_without_a_key(server: Server) -> None:
    assert httpx.get(f"{server.url}/health/live").json() == {"status": "ok"}
    assert httpx.get(f"{server.url}/health/ready").json() == {"status": "ready"}


def test_grpc_needs_the_key_but_health_does_not(server: Server) -> None:
    assert server.grpc_target is not None
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = catalign_pb2_grpc.CatalignStub(channel)
        with pytest.raises(grpc.RpcError) as refused:
            stub.ListModels(catalign_pb2.ListModelsRequest())
        listed = stub.ListModels(catalign_pb2.ListModelsRequest(), metadata=[("x-api-key", KEY)])
        with pytest.raises(grpc.RpcError) as too_many:
            stub.Register(
                catalign_pb2.RegisterRequest(points=_floats(POINT_LIMIT + 1)),
                metadata=[("x-api-key", KEY)],
            )
        health = health_pb2_grpc.HealthStub(channel)
        status = health.Check(health_pb2.HealthCheckRequest(service="catalign.v1.Catalign"))
        with pytest.raises(grpc.RpcError) as unknown:
            health.Check(health_pb2.HealthCheckRequest(service="nope"))
    assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert listed.count == 3
    assert too_many.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert status.status == health_pb2.HealthCheckResponse.SERVING
    assert unknown.value.code() == grpc.StatusCode.NOT_FOUND


def test_grpc_accepts_the_key_as_bearer_metadata(server: Server) -> None:
    assert server.grpc_target is not None
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = catalign_pb2_grpc.CatalignStub(channel)
        request = catalign_pb2.ListModelsRequest()
        listed = stub.ListModels(request, metadata=[("authorization", f"Bearer {KEY}")])
        with pytest.raises(grpc.RpcError) as wrong:
            stub.ListModels(request, metadata=[("authorization", "Bearer wrong-key-99")])
        with pytest.raises(grpc.RpcError) as basic:
            stub.ListModels(request, metadata=[("authorization", f"Basic {KEY}")])
    assert listed.count == 3
    assert wrong.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert wrong.value.details() == "wrong API key in the authorization metadata (Bearer)"
    assert basic.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert "'Bearer <key>'" in basic.value.details() and KEY not in basic.value.details()


def test_a_bug_answers_500_internal_without_its_details() -> None:
    """In process, without the lifespan: the service is not started, /models hits a stub."""

    class Broken:
        ready = False

        def models(self) -> list:
            raise RuntimeError("secret internals")

    app = create_app(ServiceSettings(grpc_port=0))
    app.dependency_overrides[get_service] = Broken

    async def ask() -> tuple[httpx.Response, httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://app") as http:
            return await http.get("/models"), await http.get("/health/ready")

    broken, ready = asyncio.run(ask())
    assert broken.status_code == 500
    assert broken.json()["error"]["code"] == "internal"
    assert "secret" not in broken.text
    assert broken.json()["request_id"] == broken.headers["x-request-id"]
    assert (ready.status_code, ready.json()) == (503, {"status": "starting"})
