"""Client and AsyncClient against httpx.MockTransport: wire format, parsing, errors, retries."""

from __future__ import annotations

import email.utils
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from catalign_client import (
    AlignResult,
    Alternative,
    APIError,
    AsyncClient,
    AuthenticationError,
    Candidate,
    CatalignError,
    Client,
    ConflictError,
    DecodingError,
    DegenerateInputError,
    InvalidInputError,
    InvalidPointsError,
    ModelInfo,
    NotFoundError,
    PayloadTooLargeError,
    PermissionDeniedError,
    ServerError,
    ServiceUnavailableError,
    Symmetry,
    TransportError,
)

CLOUD = np.array([[0.0, 0.1, 0.2], [1.5, -2.25, 3.0], [1e-3, 4.0, -5.5], [7.0, 8.0, 9.0]])


def ok(body: Any, status: int = 200) -> Callable[[httpx.Request], httpx.Response]:
    """Always answer ``body`` as JSON (NaN allowed, as Python's json writes it)."""
    content = json.dumps(body).encode()
    headers = {"Content-Type": "application/json"}
    return lambda request: httpx.Response(status, content=content, headers=headers)


def sequence(*outcomes: httpx.Response | Exception) -> Callable[[httpx.Request], httpx.Response]:
    """A handler answering (or raising) each outcome in turn."""
    pending = list(outcomes)

    def handler(request: httpx.Request) -> httpx.Response:
        outcome = pending.pop(0)
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    return handler


# Wire format ------------------------------------------------------------------------------------


def test_binary_encoding_is_little_endian_float32_with_query_options(make_api, align_answer):
    api = make_api(ok(align_answer()))
    api.align(CLOUD, top_k=5, up=(0, 0, 1), estimate_scale=True, seed=7)
    (request,) = api.requests
    assert request.method == "POST" and request.url.path == "/register"
    assert request.headers["content-type"] == "application/octet-stream"
    assert len(request.content) == 12 * len(CLOUD)
    decoded = np.frombuffer(request.content, dtype="<f4").reshape(-1, 3)
    np.testing.assert_array_equal(decoded, CLOUD.astype(np.float32))
    assert dict(request.url.params) == {
        "top_k": "5",
        "up": "0,0,1",
        "estimate_scale": "true",
        "seed": "7",
    }


def test_unset_options_are_left_to_the_server(make_api, align_answer):
    api = make_api(ok(align_answer()))
    api.align(CLOUD, up=[0.0, 0.5, 1.25])
    assert dict(api.requests[0].url.params) == {"up": "0,0.5,1.25", "estimate_scale": "false"}


def test_json_encoding_puts_points_and_options_in_the_body(make_api, align_answer):
    api = make_api(ok(align_answer()))
    api.align(CLOUD.tolist(), top_k=3, up="0,1,0", seed=1, encoding="json")
    (request,) = api.requests
    assert request.headers["content-type"] == "application/json"
    assert not request.url.params
    assert json.loads(request.content) == {
        "points": CLOUD.tolist(),
        "top_k": 3,
        "up": [0.0, 1.0, 0.0],
        "estimate_scale": False,
        "seed": 1,
    }


class _Open3DLike:
    def __init__(self, points: np.ndarray) -> None:
        self.points = list(map(tuple, points))  # like Vector3dVector: a sequence of triples


class _TrimeshLike:
    def __init__(self, vertices: np.ndarray) -> None:
        self.vertices = vertices


@pytest.mark.parametrize(
    "points",
    [
        CLOUD,
        CLOUD.tolist(),
        tuple(map(tuple, CLOUD)),
        CLOUD.astype(np.float32),
        np.asfortranarray(CLOUD),
        _Open3DLike(CLOUD),
        _TrimeshLike(CLOUD),
    ],
    ids=["float64", "lists", "tuples", "float32", "fortran", "dot-points", "dot-vertices"],
)
def test_points_are_accepted_in_every_common_container(make_api, align_answer, points):
    api = make_api(ok(align_answer()))
    api.align(points)
    decoded = np.frombuffer(api.requests[0].content, dtype="<f4").reshape(-1, 3)
    np.testing.assert_array_equal(decoded, CLOUD.astype(np.float32))


def test_integer_points_are_sent_as_floats(make_api, align_answer):
    api = make_api(ok(align_answer()))
    api.align([[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(
        np.frombuffer(api.requests[0].content, dtype="<f4"), [1, 2, 3, 4, 5, 6]
    )


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((0, 3)), "empty"),
        ([], "shape"),
        (np.zeros((5, 2)), r"shape \(N, 3\)"),
        (np.zeros(3), r"shape \(N, 3\)"),
        (np.zeros((2, 3, 1)), r"shape \(N, 3\)"),
        ([[0, 0, 0], [1, 2]], "numeric"),
        (np.array([[0.0, np.nan, 0.0], [1, 1, 1]]), "not finite"),
        (np.array([[1, 1, 1], [0.0, 0.0, np.inf]]), "first at row 1"),
        ([["a", "b", "c"]], "real numbers"),
        (np.ones((2, 3), dtype=bool), "real numbers"),
        (np.full((1, 3), 1e39), "float32"),
    ],
    ids=[
        "empty",
        "empty-list",
        "two-columns",
        "flat",
        "3d",
        "ragged",
        "nan",
        "inf",
        "strings",
        "bools",
        "float32-overflow",
    ],
)
def test_bad_points_are_refused_before_sending(make_api, points, message):
    api = make_api(ok({}))
    with pytest.raises(InvalidPointsError, match=message) as caught:
        api.align(points)
    assert isinstance(caught.value, CatalignError) and isinstance(caught.value, ValueError)
    assert api.requests == []


@pytest.mark.parametrize(
    "options",
    [
        {"top_k": 0},
        {"top_k": True},
        {"seed": -1},
        {"seed": 1.5},
        {"up": (0, 0)},
        {"up": (0, 0, 0)},
        {"up": "0,x,1"},
        {"estimate_scale": "yes"},
        {"encoding": "msgpack"},
        {"min_confidence": 1.5},
        {"min_confidence": -0.1},
        {"min_confidence": float("nan")},
        {"min_confidence": "high"},
        {"min_confidence": True},
    ],
)
def test_bad_options_are_refused_before_sending(make_api, options):
    api = make_api(ok({}))
    with pytest.raises((ValueError, TypeError)):
        api.align(CLOUD, **options)
    assert api.requests == []


@pytest.mark.parametrize("value", [1.5, "0.8", float("inf"), [0.5]])
def test_a_bad_min_confidence_is_a_value_error_naming_it(make_api, tmp_path: Path, value):
    api = make_api(ok({}))
    with pytest.raises(ValueError, match="min_confidence must be a number from 0 to 1"):
        api.align(CLOUD, min_confidence=value)
    with pytest.raises(ValueError, match="min_confidence"):
        api.align_file(tmp_path / "never-read.ply", min_confidence=value)
    assert api.requests == []


def test_min_confidence_is_sent_as_the_contract_reads_it(make_api, align_answer, tmp_path: Path):
    api = make_api(ok(align_answer()))
    api.align(CLOUD, min_confidence=0.8)
    api.align(CLOUD, min_confidence=1, encoding="json")
    path = tmp_path / "view.npy"
    np.save(path, CLOUD)
    api.align_file(path, min_confidence=0.0)
    binary, as_json, upload = api.requests
    assert binary.url.params["min_confidence"] == "0.8"
    assert json.loads(as_json.content)["min_confidence"] == 1.0
    assert upload.url.params["min_confidence"] == "0.0"


def test_align_file_uploads_multipart_with_query_options(make_api, align_answer, tmp_path: Path):
    path = tmp_path / "view.pcd"
    path.write_bytes(b"# .PCD v0.7\nFIELDS x y z\n")
    api = make_api(ok(align_answer()))
    result = api.align_file(path, top_k=2, seed=0)
    (request,) = api.requests
    assert request.headers["content-type"].startswith("multipart/form-data")
    assert b'name="file"; filename="view.pcd"' in request.content
    assert b"FIELDS x y z" in request.content
    assert dict(request.url.params) == {"top_k": "2", "estimate_scale": "false", "seed": "0"}
    assert result.model_id == "chair_0042"


def test_base_url_path_prefix_is_kept(make_api, align_answer):
    api = make_api(ok(align_answer()), base_url="http://gateway.test/catalign/")
    api.align(CLOUD)
    assert str(api.requests[0].url).startswith("http://gateway.test/catalign/register?")


def test_api_key_and_user_agent_headers(make_api):
    keyed = make_api(ok({"count": 0, "models": []}), api_key="s3cret")
    keyed.models()
    assert keyed.requests[0].headers["x-api-key"] == "s3cret"
    assert keyed.requests[0].headers["user-agent"].startswith("catalign-client/")
    anonymous = make_api(ok({"count": 0, "models": []}))
    anonymous.models()
    assert "x-api-key" not in anonymous.requests[0].headers


# Parsing -----------------------------------------------------------------------------------------


def test_align_result_is_typed_with_a_numpy_pose(make_api, align_answer):
    api = make_api(ok(align_answer(extra_field_from_a_newer_server=1)))
    result = api.align(CLOUD)
    assert result.pose.shape == (4, 4) and result.pose.dtype == np.float64
    assert not result.pose.flags.writeable
    np.testing.assert_allclose(result.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(result.rotation @ result.rotation.T, np.eye(3))
    np.testing.assert_allclose(result.translation, [0.5, -0.25, 1.0])
    assert result.scale == 2.0
    assert (result.model_id, result.request_id) == ("chair_0042", "req-123")
    assert result.num_inliers == 812 and result.points_set_aside == 3
    assert (result.fitness, result.inlier_rmse, result.inlier_ratio) == (0.91, 0.012, 0.64)
    assert result.candidates == [Candidate("chair_0042", 0.91), Candidate("c7", 0.4)]
    assert result.timings_ms == {"features": 41.5, "ransac": 12.0}
    assert (result.confidence, result.accepted, result.reason) == (0.87, True, None)
    (alternative,) = result.alternatives
    assert isinstance(alternative, Alternative)
    assert (alternative.model_id, alternative.scale) == ("c7", 1.0)
    assert (alternative.score, alternative.fitness, alternative.confidence) == (0.4, 0.55, 0.06)
    assert alternative.pose.shape == (4, 4) and not alternative.pose.flags.writeable
    np.testing.assert_allclose(alternative.rotation, np.diag([-1.0, -1.0, 1.0]))
    np.testing.assert_allclose(alternative.translation, [0.5, -0.25, 1.0])
    assert json.loads(json.dumps(result.to_dict())) == align_answer()


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda answer: [], "JSON object"),
        (lambda answer: "text", "JSON object"),
        (lambda answer: {k: v for k, v in answer.items() if k != "model_id"}, "model_id"),
        (lambda answer: {**answer, "num_inliers": "812"}, "num_inliers"),
        (lambda answer: {**answer, "candidates": [{"model_id": 1, "score": 0.5}]}, "model_id"),
        (lambda answer: {**answer, "pose": np.eye(3).tolist()}, "4x4"),
        (lambda answer: {**answer, "pose": [[float("nan")] * 4] * 4}, "4x4"),
        (lambda answer: {**answer, "confidence": "high"}, "confidence"),
        (lambda answer: {**answer, "accepted": "yes"}, "accepted"),
        (lambda answer: {**answer, "reason": 42}, "reason"),
        (lambda answer: {**answer, "alternatives": {}}, "alternatives"),
        (lambda answer: {**answer, "alternatives": [{"model_id": "c7"}]}, "4x4"),
    ],
    ids=[
        "list",
        "string",
        "no-model-id",
        "string-count",
        "bad-candidate",
        "3x3",
        "nan-pose",
        "string-confidence",
        "string-accepted",
        "number-reason",
        "alternatives-object",
        "alternative-without-pose",
    ],
)
def test_malformed_success_answers_raise_decoding_error(make_api, align_answer, mutate, message):
    api = make_api(ok(mutate(align_answer())))
    with pytest.raises(DecodingError, match=message):
        api.align(CLOUD)


def test_non_json_success_raises_decoding_error(make_api):
    api = make_api(lambda request: httpx.Response(200, text="<html>hi</html>"))
    with pytest.raises(DecodingError, match="not JSON"):
        api.models()


def test_library_calls(make_api, model_answer, tmp_path: Path):
    def handler(request: httpx.Request) -> httpx.Response:
        routes = {
            ("GET", "/models"): (200, {"count": 2, "models": [model_answer("a"), model_answer()]}),
            ("GET", "/models/a%2Fb"): (200, model_answer("a/b")),
            ("POST", "/models"): (201, model_answer("stool")),
            ("DELETE", "/models/stool"): (200, {"removed": "stool", "count": 2}),
        }
        status, body = routes[(request.method, request.url.raw_path.decode().split("?")[0])]
        return httpx.Response(status, json=body)

    api = make_api(handler)
    models = api.models()  # a server that answers in one page, without next_cursor
    assert [m.model_id for m in models] == ["a", "chair_0042"]
    assert models[1] == ModelInfo(
        "chair_0042", "/library/chair_0042.obj", "m", 2048,
        (-0.25, 0.0, -0.25), (0.25, 0.9, 0.25), (0.5, 0.9, 0.5),
        "chair", Symmetry(2, (0.0, 180.0)),
    )  # fmt: skip
    assert api.model("a/b").model_id == "a/b"
    cad = tmp_path / "stool.obj"
    cad.write_text("v 0 0 0\n")
    added = api.add_model(cad, model_id="stool", units="mm")
    upload = api.requests[2]
    assert upload.headers["content-type"].startswith("multipart/form-data")
    assert b'name="model_id"\r\n\r\nstool' in upload.content
    assert b'name="units"\r\n\r\nmm' in upload.content
    assert b'filename="stool.obj"' in upload.content
    assert added.model_id == "stool"
    assert api.remove_model("stool") == 2


def test_health_and_info(make_api, sleeps):
    answers = {"/health/ready": (200, {"status": "ready"}), "/info": (200, {"version": "0.1"})}

    def handler(request: httpx.Request) -> httpx.Response:
        status, body = answers[request.url.path]
        return httpx.Response(status, json=body)

    api = make_api(handler)
    assert api.health() is True
    assert api.info() == {"version": "0.1"}
    answers["/health/ready"] = (503, {"status": "starting"})
    assert api.health() is False
    assert sleeps == []  # health answers for now, without retrying
    answers["/health/ready"] = (401, {"error": {"code": "unauthorized", "message": "key"}})
    with pytest.raises(AuthenticationError):
        api.health()


# Errors ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("status", "code", "expected"),
    [
        (422, "invalid_input", InvalidInputError),
        (422, "invalid_file", InvalidInputError),
        (422, "degenerate_input", DegenerateInputError),
        (401, "unauthorized", AuthenticationError),
        (403, "read_only", PermissionDeniedError),
        (404, "model_not_found", NotFoundError),
        (409, "model_exists", ConflictError),
        (413, "payload_too_large", PayloadTooLargeError),
        (503, "busy", ServiceUnavailableError),
        (500, "internal", ServerError),
        (418, "teapot", APIError),
    ],
)
def test_error_statuses_map_to_typed_exceptions(make_api, error_answer, status, code, expected):
    api = make_api(
        lambda request: error_answer(status, code, "what went wrong", "rid-9"), retries=0
    )
    with pytest.raises(expected) as caught:
        api.align(CLOUD)
    error = caught.value
    assert type(error) is expected
    assert isinstance(error, APIError) and isinstance(error, CatalignError)
    assert (error.status_code, error.code, error.message) == (status, code, "what went wrong")
    assert error.request_id == "rid-9"
    assert str(error) == f"{status} {code}: what went wrong (request id rid-9)"


def test_error_hierarchy_groups_server_failures():
    assert issubclass(ServiceUnavailableError, ServerError)
    assert issubclass(DegenerateInputError, InvalidInputError)
    assert not issubclass(TransportError, APIError)


def test_non_json_error_body_still_gives_a_message(make_api):
    page = "<html><body><h1>502 Bad Gateway</h1>\n  nginx</body></html>"
    api = make_api(
        lambda request: httpx.Response(502, text=page, headers={"X-Request-ID": "edge-1"})
    )
    with pytest.raises(ServerError) as caught:
        api.models()
    assert caught.value.code is None
    assert "502 Bad Gateway" in caught.value.message and "\n" not in caught.value.message
    assert caught.value.request_id == "edge-1"


def test_empty_error_body_uses_the_reason_phrase(make_api):
    api = make_api(lambda request: httpx.Response(404))
    with pytest.raises(NotFoundError, match="Not Found"):
        api.model("nope")


def test_fastapi_default_validation_body_is_readable(make_api):
    detail = [{"loc": ["query", "top_k"], "msg": "Input should be a valid integer"}]
    api = make_api(ok({"detail": detail}, status=422))
    with pytest.raises(InvalidInputError, match=r"query\.top_k: Input should be a valid integer"):
        api.align(CLOUD)


def test_api_errors_pickle():
    import pickle

    error = NotFoundError(404, "model_not_found", "no chair_9", request_id="r1")
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is NotFoundError and str(copy) == str(error)


# Retries -----------------------------------------------------------------------------------------


def between(waits: list[float], bounds: list[tuple[float, float]]) -> bool:
    """Whether each wait lies within its (low, high) bounds, jitter included."""
    pairs = zip(waits, bounds, strict=False)
    return len(waits) == len(bounds) and all(lo <= w <= hi for w, (lo, hi) in pairs)


def test_503_is_retried_with_jittered_exponential_backoff(
    make_api, align_answer, error_answer, sleeps
):
    busy = error_answer(503, "busy", "queue full")
    api = make_api(sequence(busy, busy, httpx.Response(200, json=align_answer())), backoff=0.2)
    assert api.align(CLOUD).model_id == "chair_0042"
    assert len(api.requests) == 3
    assert between(sleeps, [(0.1, 0.2), (0.2, 0.4)]), sleeps
    assert api.requests[0].content == api.requests[2].content


def test_503_gives_up_after_the_retries(make_api, error_answer, sleeps):
    api = make_api(lambda request: error_answer(503, "busy", "queue full"), retries=3, backoff=0.1)
    with pytest.raises(ServiceUnavailableError, match="queue full"):
        api.align(CLOUD)
    assert len(api.requests) == 4
    assert between(sleeps, [(0.05, 0.1), (0.1, 0.2), (0.2, 0.4)]), sleeps


@pytest.mark.parametrize("status", [502, 504])
def test_a_proxys_502_and_504_are_retried(make_api, align_answer, sleeps, status):
    api = make_api(sequence(httpx.Response(status), httpx.Response(200, json=align_answer())))
    assert api.align(CLOUD).model_id == "chair_0042"
    assert len(api.requests) == 2 and len(sleeps) == 1


def test_retry_after_is_honoured_and_capped(make_api, align_answer, sleeps):
    def busy(seconds: str) -> httpx.Response:
        body = {"error": {"code": "busy", "message": "later"}, "request_id": "r"}
        return httpx.Response(503, json=body, headers={"Retry-After": seconds})

    api = make_api(sequence(busy("3"), busy("3600"), httpx.Response(200, json=align_answer())))
    api.align(CLOUD)
    assert between(sleeps, [(3.0, 3.6), (10.0, 10.0)]), sleeps


def test_retry_after_as_http_date(make_api, align_answer, sleeps):
    when = email.utils.formatdate(time.time() + 5, usegmt=True)
    busy = httpx.Response(503, headers={"Retry-After": when}, text="busy")
    api = make_api(sequence(busy, httpx.Response(200, json=align_answer())))
    api.align(CLOUD)
    assert 3.0 < sleeps[0] <= 6.0


def test_service_unavailable_exposes_retry_after(make_api):
    api = make_api(lambda request: httpx.Response(503, headers={"Retry-After": "7"}), retries=0)
    with pytest.raises(ServiceUnavailableError) as caught:
        api.models()
    assert caught.value.retry_after == 7.0


def test_connection_errors_are_retried(make_api, align_answer, sleeps):
    refused = httpx.ConnectError("connection refused")
    api = make_api(sequence(refused, refused, httpx.Response(200, json=align_answer())))
    assert api.align(CLOUD).model_id == "chair_0042"
    assert between(sleeps, [(0.1, 0.2), (0.2, 0.4)]), sleeps


def test_connection_errors_end_in_transport_error(make_api, sleeps):
    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused")

    api = make_api(refuse, retries=1)
    with pytest.raises(TransportError, match=r"2 attempt.*connection refused") as caught:
        api.models()
    assert isinstance(caught.value.__cause__, httpx.ConnectError)
    assert len(sleeps) == 1


def test_timeouts_are_retried_only_where_resending_is_harmless(
    make_api, align_answer, model_answer, tmp_path: Path, sleeps
):
    api = make_api(sequence(httpx.ReadTimeout("slow"), httpx.Response(200, json=align_answer())))
    assert api.align(CLOUD).model_id == "chair_0042"  # registration is a pure function
    cad = tmp_path / "stool.obj"
    cad.write_text("v 0 0 0\n")
    adding = make_api(sequence(httpx.ReadTimeout("slow"), httpx.Response(201, json={})))
    with pytest.raises(TransportError, match="1 attempt"):
        adding.add_model(cad)  # the model may have been added: do not add it twice
    refused_then_ok = sequence(
        httpx.ConnectError("refused"), httpx.Response(201, json=model_answer("stool"))
    )
    adding = make_api(refused_then_ok)
    assert adding.add_model(cad).model_id == "stool"  # nothing reached the server: resend
    keyed = make_api(
        sequence(httpx.ReadTimeout("slow"), httpx.Response(201, json=model_answer("stool")))
    )
    assert keyed.add_model(cad, idempotency_key="k-1").model_id == "stool"  # answered once
    assert [r.headers["idempotency-key"] for r in keyed.requests] == ["k-1", "k-1"]


@pytest.mark.parametrize("status", [502, 503, 504])
def test_a_library_change_without_a_key_is_not_resent_after_an_answer(
    make_api, model_answer, sleeps, tmp_path: Path, status
):
    cad = tmp_path / "stool.obj"
    cad.write_text("v 0 0 0\n")
    api = make_api(sequence(httpx.Response(status), httpx.Response(201, json=model_answer())))
    with pytest.raises(ServerError):
        api.add_model(cad)
    removing = make_api(sequence(httpx.Response(status), httpx.Response(200, json={})))
    with pytest.raises(ServerError):
        removing.remove_model("stool")
    assert len(api.requests) == len(removing.requests) == 1 and sleeps == []
    assert "idempotency-key" not in api.requests[0].headers


def test_a_generated_idempotency_key_is_a_uuid_kept_across_retries(make_api, sleeps):
    api = make_api(
        sequence(httpx.Response(503), httpx.Response(200, json={"removed": "a", "count": 1}))
    )
    assert api.remove_model("a", idempotency_key=True) == 1
    first, second = (r.headers["idempotency-key"] for r in api.requests)
    assert first == second and len(first) == 36 and first.count("-") == 4


@pytest.mark.parametrize("key", ["", "with space", "é", "x" * 256, 7])
def test_a_bad_idempotency_key_is_refused_before_sending(make_api, key):
    api = make_api(lambda request: httpx.Response(200, json={"removed": "a", "count": 1}))
    with pytest.raises(ValueError, match="idempotency_key"):
        api.remove_model("a", idempotency_key=key)
    assert api.requests == []


@pytest.mark.parametrize("status", [400, 401, 404, 409, 413, 422, 500])
def test_client_errors_and_500_are_not_retried(make_api, error_answer, sleeps, status):
    api = make_api(lambda request: error_answer(status, "x", "no"))
    with pytest.raises(APIError):
        api.align(CLOUD)
    assert len(api.requests) == 1
    assert sleeps == []


def test_invalid_retry_options():
    with pytest.raises(ValueError, match="retries"):
        Client("http://x", retries=-1)
    with pytest.raises(ValueError, match="backoff"):
        AsyncClient("http://x", backoff=float("nan"))
    with pytest.raises(ValueError, match="retry_budget"):
        Client("http://x", retry_budget=-1.0)


# Lifecycle ---------------------------------------------------------------------------------------


def test_sync_client_is_a_context_manager(align_answer):
    transport = httpx.MockTransport(ok(align_answer()))
    with Client("http://catalign.test", transport=transport) as client:
        assert client.align(CLOUD).model_id == "chair_0042"
        assert not client.is_closed
    assert client.is_closed
    assert repr(client) == "Client(base_url='http://catalign.test')"


def test_async_client_is_an_async_context_manager(align_answer):
    import asyncio

    async def use() -> AsyncClient:
        transport = httpx.MockTransport(ok(align_answer()))
        async with AsyncClient("http://catalign.test", transport=transport) as client:
            assert (await client.align(CLOUD)).model_id == "chair_0042"
            assert not client.is_closed
        return client

    assert asyncio.run(use()).is_closed


def test_the_answer_says_which_up_it_used(align_answer):
    estimated = AlignResult.from_json(align_answer(up=[0.0, 1.0, 0.0], up_estimated=True))
    assert estimated.up == (0.0, 1.0, 0.0) and estimated.up_estimated
    assert estimated.to_dict()["up"] == [0.0, 1.0, 0.0]
    # an answer without the fields (an older server) keeps the request's up, not estimated
    older = {k: v for k, v in align_answer().items() if k not in ("up", "up_estimated")}
    parsed = AlignResult.from_json(older, up=(0.0, 0.0, 1.0))
    assert parsed.up == (0.0, 0.0, 1.0) and not parsed.up_estimated
    assert AlignResult.from_json(align_answer(up=None)).up is None


def test_an_answer_below_min_confidence_keeps_its_pose_and_says_why(align_answer):
    reason = "confidence 0.42 is below min_confidence 0.80: ask for another view"
    result = AlignResult.from_json(
        align_answer(confidence=0.42, accepted=False, reason=reason, alternatives=[])
    )
    assert not result.accepted and result.reason == reason and result.confidence == 0.42
    assert result.pose.shape == (4, 4) and result.alternatives == []
    assert result.to_dict()["accepted"] is False and result.to_dict()["reason"] == reason


def test_an_answer_without_a_calibrator_has_no_confidence(align_answer):
    result = AlignResult.from_json(align_answer(confidence=None))
    assert result.confidence is None and result.accepted
    assert result.to_dict()["confidence"] is None


def test_an_older_servers_answer_is_accepted_without_alternatives(align_answer):
    new = ("confidence", "accepted", "reason", "alternatives")
    older = {k: v for k, v in align_answer().items() if k not in new}
    result = AlignResult.from_json(older)
    assert (result.confidence, result.accepted, result.reason) == (None, True, None)
    assert result.alternatives == []
