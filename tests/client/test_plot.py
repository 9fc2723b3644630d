"""Pictures of an alignment, the model points they need, and ``catalign-client align --png``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from matplotlib import image as matplotlib_image

from catalign_client import AlignResult, Client, DecodingError, NotFoundError
from catalign_client._cli import main

OBSERVED = np.random.default_rng(0).uniform(-1, 1, size=(200, 3))
MODEL = np.random.default_rng(1).uniform(-0.5, 0.5, size=(300, 3))
INSTALL = 'pip install "catalign-client[plot]"'


def posed(result: AlignResult) -> np.ndarray:
    return MODEL @ result.pose[:3, :3].T + result.pose[:3, 3]


def scatter(ax: Any, prefix: str) -> np.ndarray:
    """The data of the scatter whose label starts with ``prefix``."""
    (collection,) = [c for c in ax.collections if c.get_label().startswith(prefix)]
    return np.asarray(collection.get_offsets())


def test_plot_draws_three_views_and_writes_a_png(align_answer, tmp_path: Path):
    result = AlignResult.from_json(align_answer(), up=(0, 0, 1))
    path = tmp_path / "alignment.png"
    figure = result.plot(OBSERVED, MODEL, path, title="kitchen")
    assert len(figure.axes) == 3
    assert [ax.get_title() for ax in figure.axes] == ["top", "front", "side"]
    heading = figure.get_suptitle()
    assert "kitchen" in heading and "chair_0042" in heading and "fitness 0.910" in heading
    assert path.stat().st_size > 0
    pixels = matplotlib_image.imread(path)[..., :3]
    assert pixels.shape[0] > 300 and pixels.shape[1] > 900
    inked = (pixels < 0.9).any(axis=-1).mean()
    assert 0.01 < inked < 0.9, "the picture is blank or solid"
    red, blue = pixels[..., 0], pixels[..., 2]
    orange, blue = red - blue > 0.3, blue - red > 0.2
    assert orange.sum() > 100 and blue.sum() > 100, "both clouds are visible"


def test_the_model_is_drawn_where_the_pose_puts_it(align_answer):
    result = AlignResult.from_json(align_answer())
    figure = result.plot(OBSERVED.tolist(), MODEL)
    model, seen = posed(result), OBSERVED
    for ax, (h, v) in zip(figure.axes, [(0, 1), (0, 2), (1, 2)], strict=True):
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("xyz"[h], "xyz"[v])
        np.testing.assert_allclose(scatter(ax, "chair_0042"), model[:, [h, v]])
        np.testing.assert_allclose(scatter(ax, "observed"), seen[:, [h, v]])


def test_views_follow_up_or_fall_back_to_coordinate_planes(align_answer):
    y_up = AlignResult.from_json(align_answer(up=[0.0, 2.0, 0.0])).plot(OBSERVED, MODEL)
    labels = [(ax.get_title(), ax.get_xlabel(), ax.get_ylabel()) for ax in y_up.axes]
    assert labels == [("top", "x", "-z"), ("front", "x", "y"), ("side", "-z", "y")]
    front = scatter(y_up.axes[1], "observed")
    np.testing.assert_allclose(front, OBSERVED[:, [0, 1]])

    no_up = AlignResult.from_json(align_answer(up=None)).plot(OBSERVED, MODEL)
    assert [ax.get_title() for ax in no_up.axes] == ["x-y", "x-z", "y-z"]


def test_plot_without_matplotlib_says_how_to_install(align_answer, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    result = AlignResult.from_json(align_answer())
    with pytest.raises(ImportError, match=r'pip install "catalign-client\[plot\]"'):
        result.plot(OBSERVED, MODEL)


def test_the_sdk_imports_and_aligns_without_matplotlib():
    code = (
        "import sys; sys.modules['matplotlib'] = None\n"
        "import httpx, numpy as np, catalign_client as sdk\n"
        "from catalign_client import _cli\n"
        "handler = lambda r: httpx.Response(200, content=np.zeros(6, '<f4').tobytes())\n"
        "with sdk.Client('http://c.test', transport=httpx.MockTransport(handler)) as client:\n"
        "    assert client.model_points('m').shape == (2, 3)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


# Client.model_points ----------------------------------------------------------------------------


def points_answer(points: np.ndarray, count: str | None = None) -> httpx.Response:
    headers = {"Content-Type": "application/octet-stream"}
    headers["X-Point-Count"] = count if count is not None else str(len(points))
    return httpx.Response(200, content=points.astype("<f4").tobytes(), headers=headers)


def test_model_points_parses_raw_float32(make_api):
    api = make_api(lambda request: points_answer(MODEL))
    points = api.model_points("chair/0042", max_points=2000)
    (request,) = api.requests
    assert (
        request.method == "GET"
        and request.url.raw_path == b"/models/chair%2F0042/points?max_points=2000"
    )
    assert points.shape == (300, 3) and points.dtype == np.float64
    np.testing.assert_array_equal(points, MODEL.astype(np.float32))
    api.model_points("c")
    assert api.requests[-1].url.params["max_points"] == "5000"


@pytest.mark.parametrize(
    ("answer", "error", "message"),
    [
        (lambda: httpx.Response(200, content=b"\0" * 13), DecodingError, "13 bytes"),
        (lambda: points_answer(MODEL, count="299"), DecodingError, "X-Point-Count says 299"),
        (
            lambda: httpx.Response(
                404, json={"error": {"code": "model_not_found", "message": "no c"}}
            ),
            NotFoundError,
            "no c",
        ),
    ],
)
def test_model_points_errors(make_api, answer, error, message):
    api = make_api(lambda request: answer())
    with pytest.raises(error, match=message):
        api.model_points("c")


@pytest.mark.parametrize("max_points", [0, -1, 2.5, True])
def test_model_points_refuses_bad_limits_before_sending(make_api, max_points):
    api = make_api(lambda request: points_answer(MODEL))
    with pytest.raises(ValueError, match="max_points must be a positive integer"):
        api.model_points("c", max_points=max_points)
    assert api.requests == []


# catalign-client align --png --------------------------------------------------------------------


@pytest.fixture
def server(align_answer) -> dict[str, Any]:
    state: dict[str, Any] = {"requests": []}
    routes = {
        ("POST", "/register"): httpx.Response(200, json=align_answer()),
        ("GET", "/models/chair_0042/points"): points_answer(MODEL),
    }

    def handler(request: httpx.Request) -> httpx.Response:
        request.read()
        state["requests"].append(request)
        return routes[(request.method, request.url.path)]

    state["factory"] = lambda url, key: Client(url, transport=httpx.MockTransport(handler))
    return state


def test_cli_png_draws_the_alignment_and_still_prints_json(
    server, capsys, tmp_path: Path, align_answer
):
    np.save(tmp_path / "view.npy", OBSERVED)
    png = tmp_path / "out.png"
    argv = ["align", str(tmp_path / "view.npy"), "--url", "http://c.test", "--up", "0,0,1"]
    assert main([*argv, "--png", str(png)], client_factory=server["factory"]) == 0
    out = capsys.readouterr()
    assert out.err == "" and json.loads(out.out) == align_answer()
    assert [(r.method, r.url.path) for r in server["requests"]] == [
        ("POST", "/register"),
        ("GET", "/models/chair_0042/points"),
    ]
    assert png.stat().st_size > 0
    assert (matplotlib_image.imread(png)[..., :3] < 0.9).any()


@pytest.mark.parametrize(
    ("block", "name", "message"),
    [
        (True, "view.npy", f"--png needs matplotlib, which is not installed: {INSTALL}"),
        (False, "view.pcd", "--png draws the points read here, and view.pcd is not a file"),
    ],
)
def test_cli_png_usage_errors_exit_2_before_sending(
    server, capsys, tmp_path: Path, monkeypatch, block, name, message
):
    if block:
        monkeypatch.setitem(sys.modules, "matplotlib", None)
    np.save(tmp_path / "view.npy", OBSERVED)
    (tmp_path / "view.pcd").write_text("# .PCD v0.7\n")
    argv = ["align", str(tmp_path / name), "--url", "http://c.test", "--png", "out.png"]
    assert main(argv, client_factory=server["factory"]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.startswith(f"catalign-client: error: {message}")
    assert out.err.count("\n") == 1
    assert server["requests"] == []
