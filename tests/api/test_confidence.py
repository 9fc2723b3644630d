"""Confidence, alternatives and ``min_confidence`` through a real server: HTTP (JSON, binary and
file bodies), gRPC and the SDK give the same fields, and the same acceptance, from one rule.

The confidence's values come from the weights' calibrator (a development one may be in
``model_store/`` now), so the tests check its shape and its consistency with whether the weights
have a calibrator, never its values; a second server on the same weights without their
calibrator checks the other case.
"""

from __future__ import annotations

import asyncio
import io
import math
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import grpc
import httpx
import numpy as np
import pytest

import catalign_client as sdk
from catalign.api import catalign_pb2, catalign_pb2_grpc
from catalign.api.schemas import acceptance
from catalign.geometry.se3 import rotation_error_deg, split_scale
from catalign.registration.decision.confidence import find_calibrator

if TYPE_CHECKING:
    from tests.api.conftest import Server, View

BINARY = {"content-type": "application/octet-stream"}
LIBRARY = {"proc-0000", "proc-0001", "proc-0002"}
OPTIONS = {"seed": 3}  # every model tried: alternatives of other models too
NUMBER = r"\d+\.\d+"


@pytest.fixture(scope="module")
def server(library_dir: Path, serve: Callable) -> Iterator[Server]:
    with serve(library=library_dir, grpc=True, workers=1, queue=4) as running:
        yield running


@pytest.fixture(scope="module")
def calibrated(server: Server) -> bool:
    """Whether the served weights have a confidence calibrator."""
    return find_calibrator(server.settings.model_dir) is not None


@pytest.fixture(scope="module")
def client(server: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=120) as http:
        yield http


@pytest.fixture(scope="module")
def view(views: Callable[..., View]) -> View:
    return views(seed=1)


@pytest.fixture(scope="module")
def answer(client: httpx.Client, view: View) -> dict:
    response = client.post("/register", json={"points": view.points.tolist(), **OPTIONS})
    assert response.status_code == 200, response.text
    return response.json()


def check_confidence(value: object, calibrated: bool) -> None:
    if calibrated:
        assert isinstance(value, float) and 0.0 <= value <= 1.0, value
    else:
        assert value is None


def check_alternatives(body: dict, calibrated: bool) -> None:
    """Each alternative a well-formed pose of a library model, a different answer from the
    winner (another model, or the same one turned by more than 30 degrees), best first."""
    alternatives = body["alternatives"]
    assert isinstance(alternatives, list) and len(alternatives) <= 3
    winner, _ = split_scale(np.array(body["pose"]))
    scores = [a["score"] for a in alternatives]
    assert scores == sorted(scores, reverse=True)
    for alternative in alternatives:
        assert set(alternative) == {"model_id", "pose", "scale", "score", "fitness", "confidence"}
        assert alternative["model_id"] in LIBRARY
        pose = np.array(alternative["pose"])
        assert pose.shape == (4, 4) and np.isfinite(pose).all()
        np.testing.assert_allclose(pose[3], [0, 0, 0, 1], atol=1e-12)
        rigid, scale = split_scale(pose)
        assert scale == pytest.approx(alternative["scale"], rel=1e-9)
        rotation = rigid[:3, :3]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
        assert 0.0 <= alternative["fitness"] <= 1.0
        check_confidence(alternative["confidence"], calibrated)
        if alternative["model_id"] == body["model_id"]:
            assert rotation_error_deg(rotation, winner[:3, :3]) > 30.0


def check_refused(body: dict, calibrated: bool, threshold: str = "1.00") -> None:
    """``accepted`` false with a reason naming the confidence and the threshold (or saying
    that there is no calibrator); the pose is there all the same."""
    assert body["accepted"] is False
    reason = body["reason"]
    assert isinstance(reason, str) and f"min_confidence {threshold}" in reason
    if calibrated:
        (shown,) = re.findall(rf"^confidence ({NUMBER}) is below", reason)
        assert float(shown) == pytest.approx(body["confidence"], abs=0.01)
        assert float(shown) < float(threshold)
    else:
        assert "no confidence calibrator" in reason
    assert len(body["pose"]) == 4


# HTTP ------------------------------------------------------------------------------------------


def test_the_answer_has_confidence_and_alternatives(answer: dict, calibrated: bool) -> None:
    check_confidence(answer["confidence"], calibrated)
    assert answer["accepted"] is True and answer["reason"] is None
    check_alternatives(answer, calibrated)


def test_min_confidence_in_a_json_body(
    client: httpx.Client, view: View, answer: dict, calibrated: bool
) -> None:
    points = view.points.tolist()
    strict = client.post("/register", json={"points": points, **OPTIONS, "min_confidence": 1.0})
    lenient = client.post("/register", json={"points": points, **OPTIONS, "min_confidence": 0})
    assert strict.status_code == lenient.status_code == 200, (strict.text, lenient.text)
    check_refused(strict.json(), calibrated)
    assert lenient.json()["accepted"] is calibrated  # unknown confidence meets no threshold
    for body in (strict.json(), lenient.json()):  # the same answer, only judged
        assert body["model_id"] == answer["model_id"]
        np.testing.assert_allclose(body["pose"], answer["pose"], atol=1e-9)
        assert body["confidence"] == answer["confidence"]
        assert len(body["alternatives"]) == len(answer["alternatives"])


def test_min_confidence_as_a_query_parameter(
    client: httpx.Client, view: View, answer: dict, calibrated: bool
) -> None:
    buffer = io.BytesIO()
    np.save(buffer, view.points)
    params = {**OPTIONS, "min_confidence": "1"}
    binary = client.post("/register", content=view.points.tobytes(), params=params, headers=BINARY)
    upload = client.post("/register", files={"file": ("v.npy", buffer.getvalue())}, params=params)
    for response in (binary, upload):
        assert response.status_code == 200, response.text
        check_refused(response.json(), calibrated)
        np.testing.assert_allclose(response.json()["pose"], answer["pose"], atol=1e-9)
    lenient = client.post(
        "/register",
        content=view.points.tobytes(),
        params={**OPTIONS, "min_confidence": "0.0"},
        headers=BINARY,
    )
    assert lenient.status_code == 200, lenient.text
    assert lenient.json()["accepted"] is calibrated


@pytest.mark.parametrize(
    ("json_value", "query_value"),
    [(1.5, "1.5"), (-0.1, "-0.1"), ("high", "high"), (True, "nan"), (None, "inf")],
)
def test_a_bad_min_confidence_is_refused_in_a_sentence(
    client: httpx.Client, view: View, json_value: object, query_value: str
) -> None:
    points = view.points[:200]
    responses = [
        client.post(
            "/register",
            content=points.tobytes(),
            params={"min_confidence": query_value},
            headers=BINARY,
        )
    ]
    if json_value is not None:
        body = {"points": points.tolist(), "min_confidence": json_value}
        responses.append(client.post("/register", json=body))
    for response in responses:
        assert response.status_code == 422, response.text
        error = response.json()["error"]
        assert error["code"] == "invalid_input" and "min_confidence" in error["message"]


def test_a_nan_min_confidence_in_json_is_refused(client: httpx.Client) -> None:
    body = b'{"points": [[0, 0, 0], [1, 1, 1]], "min_confidence": NaN}'
    response = client.post("/register", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 422
    assert "min_confidence" in response.json()["error"]["message"]


def test_with_a_json_body_min_confidence_goes_in_the_body(client: httpx.Client, view: View) -> None:
    response = client.post(
        "/register", json={"points": view.points[:200].tolist()}, params={"min_confidence": "0.5"}
    )
    assert response.status_code == 422
    assert "min_confidence" in response.json()["error"]["message"]


# gRPC ------------------------------------------------------------------------------------------


def test_grpc_carries_the_same_confidence_alternatives_and_acceptance(
    server: Server, view: View, answer: dict, calibrated: bool
) -> None:
    assert server.grpc_target is not None
    request = {"points": view.points.tobytes(), **OPTIONS}
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = catalign_pb2_grpc.CatalignStub(channel)
        plain = stub.Register(catalign_pb2.RegisterRequest(**request))
        strict = stub.Register(catalign_pb2.RegisterRequest(**request, min_confidence=1.0))
        lenient = stub.Register(catalign_pb2.RegisterRequest(**request, min_confidence=0.0))
        refusals = []
        for bad in (1.5, -0.5, math.nan):
            with pytest.raises(grpc.RpcError) as refused:
                stub.Register(catalign_pb2.RegisterRequest(**request, min_confidence=bad))
            refusals.append(refused.value)

    assert plain.HasField("confidence") is calibrated
    if calibrated:
        assert plain.confidence == answer["confidence"]
    assert plain.accepted and plain.reason == ""
    alternatives = [
        {
            "model_id": a.model_id,
            "pose": np.reshape(a.pose, (4, 4)).tolist(),
            "scale": a.scale,
            "score": a.score,
            "fitness": a.fitness,
            "confidence": a.confidence if a.HasField("confidence") else None,
        }
        for a in plain.alternatives
    ]
    assert alternatives == answer["alternatives"]
    check_alternatives({**answer, "alternatives": alternatives}, calibrated)

    assert not strict.accepted
    check_refused(
        {
            "accepted": strict.accepted,
            "reason": strict.reason,
            "confidence": strict.confidence if strict.HasField("confidence") else None,
            "pose": np.reshape(strict.pose, (4, 4)).tolist(),
        },
        calibrated,
    )
    assert lenient.accepted is calibrated
    for error in refusals:
        assert error.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "min_confidence" in (error.details() or "")
        assert ("catalign-error-code", "invalid_input") in error.trailing_metadata()


# SDK -------------------------------------------------------------------------------------------


def test_the_sdk_round_trips_the_new_fields(
    server: Server, view: View, answer: dict, calibrated: bool, tmp_path: Path
) -> None:
    path = tmp_path / "view.npy"
    np.save(path, view.points)
    with sdk.Client(server.url, timeout=120) as client:
        result = client.align(view.points, **OPTIONS)
        strict = client.align(view.points, min_confidence=1.0, encoding="json", **OPTIONS)
        from_file = client.align_file(path, min_confidence=0.0, **OPTIONS)
        with pytest.raises(ValueError, match="min_confidence"):
            client.align(view.points, min_confidence=2.0)

    assert result.confidence == answer["confidence"]
    check_confidence(result.confidence, calibrated)
    assert result.accepted and result.reason is None
    assert [a.to_dict() for a in result.alternatives] == answer["alternatives"]
    for alternative in result.alternatives:
        assert isinstance(alternative, sdk.Alternative)
        assert alternative.pose.shape == (4, 4) and not alternative.pose.flags.writeable
        np.testing.assert_allclose(
            alternative.rotation @ alternative.rotation.T, np.eye(3), atol=1e-6
        )
    check_refused(strict.to_dict(), calibrated)
    assert from_file.accepted is calibrated
    np.testing.assert_allclose(strict.pose, result.pose, atol=1e-6)


def test_the_async_sdk_sends_min_confidence(server: Server, view: View, calibrated: bool) -> None:
    async def run() -> sdk.AlignResult:
        async with sdk.AsyncClient(server.url, timeout=120) as client:
            return await client.align(view.points, min_confidence=1.0, **OPTIONS)

    check_refused(asyncio.run(run()).to_dict(), calibrated)


# Weights without a calibrator --------------------------------------------------------------------


@pytest.fixture(scope="module")
def uncalibrated_model_dir(model_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The served weights without their calibrator (links to everything else)."""
    folder = tmp_path_factory.mktemp("uncalibrated") / "model"
    folder.mkdir()
    for item in model_dir.iterdir():
        if item.name != "confidence":
            (folder / item.name).symlink_to(item.resolve())
    return folder


def test_weights_without_a_calibrator_answer_null_and_cannot_meet_a_threshold(
    library_dir: Path,
    uncalibrated_model_dir: Path,
    serve: Callable,
    view: View,
) -> None:
    assert find_calibrator(uncalibrated_model_dir) is None
    points = view.points.tolist()
    with (
        serve(library=library_dir, model_dir=uncalibrated_model_dir, workers=1) as server,
        httpx.Client(base_url=server.url, timeout=120) as http,
    ):
        plain = http.post("/register", json={"points": points, **OPTIONS}).json()
        lenient = http.post("/register", json={"points": points, "min_confidence": 0.0}).json()
    assert plain["confidence"] is None and plain["accepted"] is True
    check_alternatives(plain, calibrated=False)
    check_refused(lenient, calibrated=False, threshold="0.00")


# The rule ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("confidence", "min_confidence", "accepted", "reason"),
    [
        (0.42, None, True, None),
        (None, None, True, None),
        (0.42, 0.8, False, "confidence 0.42 is below min_confidence 0.80: ask for another view"),
        (0.7999, 0.8, False, "confidence 0.7999 is below min_confidence 0.80"),
        (0.5, 0.825, False, "confidence 0.50 is below min_confidence 0.825"),
        (0.8, 0.8, True, None),
        (1.0, 1.0, True, None),
        (0.0, 0.0, True, None),
        (None, 0.0, False, "no confidence calibrator, so min_confidence 0.00 cannot be met"),
    ],
)
def test_the_acceptance_rule(
    confidence: float | None, min_confidence: float | None, accepted: bool, reason: str | None
) -> None:
    got_accepted, got_reason = acceptance(confidence, min_confidence)
    assert got_accepted is accepted
    if reason is None:
        assert got_reason is None
    else:
        assert got_reason is not None and reason in got_reason
