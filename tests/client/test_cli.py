"""The catalign-client CLI against a mock server: JSON out, one line and status 1 on errors."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from catalign_client import Client
from catalign_client._cli import main

POINTS = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture
def server(align_answer, model_answer) -> dict[str, Any]:
    """A mock server's routes and the requests it saw; ``factory`` builds clients for main()."""
    state: dict[str, Any] = {
        "requests": [],
        "routes": {
            ("POST", "/register"): httpx.Response(200, json=align_answer()),
            ("GET", "/models"): httpx.Response(200, json={"count": 1, "models": [model_answer()]}),
        },
    }

    def handler(request: httpx.Request) -> httpx.Response:
        request.read()
        state["requests"].append(request)
        route = state["routes"][(request.method, request.url.path)]
        if isinstance(route, Exception):
            raise route
        return route

    def factory(url: str, api_key: str | None) -> Client:
        state["url"], state["api_key"] = url, api_key
        return Client(url, api_key=api_key, transport=httpx.MockTransport(handler))

    state["factory"] = factory
    return state


def run(server: dict[str, Any], *argv: str) -> int:
    factory: Callable[[str, str | None], Client] = server["factory"]
    return main(list(argv), client_factory=factory)


def test_align_npy_prints_the_result_as_json(server, capsys, tmp_path: Path, align_answer):
    np.save(tmp_path / "view.npy", POINTS)
    argv = ["align", str(tmp_path / "view.npy"), "--url", "http://c.test", "--api-key", "k"]
    status = run(server, *argv, "--top-k", "4", "--up", "0,0,1", "--seed", "3")
    out = capsys.readouterr()
    assert status == 0 and out.err == ""
    assert json.loads(out.out) == align_answer()
    (request,) = server["requests"]
    assert server["api_key"] == "k"
    assert request.headers["content-type"] == "application/octet-stream"
    assert len(request.content) == 12 * len(POINTS)
    assert dict(request.url.params) == {
        "top_k": "4",
        "up": "0,0,1",
        "estimate_scale": "false",
        "seed": "3",
    }


def test_align_other_formats_are_uploaded(server, capsys, tmp_path: Path):
    path = tmp_path / "view.pcd"
    path.write_text("# .PCD v0.7\n")
    assert run(server, "align", str(path), "--url", "http://c.test", "--estimate-scale") == 0
    (request,) = server["requests"]
    assert request.headers["content-type"].startswith("multipart/form-data")
    assert request.url.params["estimate_scale"] == "true"
    assert json.loads(capsys.readouterr().out)["pose"][3] == [0, 0, 0, 1]


def test_an_answer_below_min_confidence_is_printed_and_named_on_stderr(
    server, capsys, tmp_path: Path, align_answer
):
    reason = "confidence 0.42 is below min_confidence 0.80: ask for another view"
    answer = align_answer(confidence=0.42, accepted=False, reason=reason)
    server["routes"][("POST", "/register")] = httpx.Response(200, json=answer)
    np.save(tmp_path / "view.npy", POINTS)
    argv = ["align", str(tmp_path / "view.npy"), "--url", "http://c.test"]
    assert run(server, *argv, "--min-confidence", "0.8") == 0
    out = capsys.readouterr()
    printed = json.loads(out.out)
    assert printed == answer and printed["confidence"] == 0.42 and printed["pose"]
    assert out.err == f"catalign-client: not accepted: {reason}\n"
    (request,) = server["requests"]
    assert request.url.params["min_confidence"] == "0.8"


def test_a_bad_min_confidence_exits_1_before_sending(server, capsys, tmp_path: Path):
    np.save(tmp_path / "view.npy", POINTS)
    argv = ["align", str(tmp_path / "view.npy"), "--url", "http://c.test"]
    assert run(server, *argv, "--min-confidence", "1.5") == 1
    assert "min_confidence must be a number from 0 to 1" in capsys.readouterr().err
    assert server["requests"] == []


def test_models_prints_the_library(server, capsys, monkeypatch):
    monkeypatch.setenv("CATALIGN_URL", "http://from-env.test")
    assert run(server, "models") == 0
    assert server["url"] == "http://from-env.test"
    printed = json.loads(capsys.readouterr().out)
    assert printed["count"] == 1 and printed["models"][0]["model_id"] == "chair_0042"


def test_server_errors_exit_1_with_one_line(server, capsys, tmp_path: Path, error_answer):
    np.save(tmp_path / "view.npy", POINTS)
    server["routes"][("POST", "/register")] = error_answer(
        422, "degenerate_input", "points are\ncollinear", "rid-7"
    )
    assert run(server, "align", str(tmp_path / "view.npy"), "--url", "http://c.test") == 1
    out = capsys.readouterr()
    assert out.out == ""
    assert out.err == (
        "catalign-client: error: 422 degenerate_input: points are collinear (request id rid-7)\n"
    )


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["align", "missing.npy", "--url", "http://c.test"], "No such file"),
        (["align", "{bad}", "--url", "http://c.test"], "not finite"),
        (["align", "{bad}"], "no server URL"),
        (["align", "good.xyz", "--url", "http://c.test", "--up", "0,0"], "up must be"),
        (["models", "--url", "http://c.test"], "ConnectError"),
    ],
)
def test_local_errors_exit_1(server, capsys, tmp_path, monkeypatch, argv, message):
    monkeypatch.delenv("CATALIGN_URL", raising=False)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.xyz").write_text("0 0 nan\n")
    (tmp_path / "good.xyz").write_text("0 0 1\n")
    server["routes"][("GET", "/models")] = httpx.ConnectError("refused")
    argv = [arg.replace("{bad}", "bad.xyz") for arg in argv]
    assert run(server, *argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("catalign-client: error: ") and message in err
    assert err.count("\n") == 1
