"""The README's quick-start examples, run as written against a real server."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

if TYPE_CHECKING:
    from tests.api.conftest import Server, View

README = Path(__file__).resolve().parents[2] / "README.md"


def _blocks(language: str) -> list[str]:
    text = README.read_text().split("## Quick start", 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{language}\n(.*?)```", text, flags=re.S)


@pytest.fixture(scope="module")
def server(library_dir: Path, serve: Callable) -> Iterator[Server]:
    with serve(library=library_dir, workers=1, queue=2) as running:
        yield running


@pytest.fixture
def cloud_dir(tmp_path: Path, views: Callable[..., View], monkeypatch) -> Path:
    np.save(tmp_path / "cloud.npy", views(seed=2, yaw=2.5).points)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_the_sdk_example_runs_as_written(server: Server, cloud_dir: Path, capsys) -> None:
    (code,) = _blocks("python")
    exec(compile(code.replace("http://127.0.0.1:8000", server.url), "README", "exec"), {})
    printed = capsys.readouterr().out
    assert printed.split()[0].startswith("proc-")


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_the_curl_examples_run_as_written(server: Server, cloud_dir: Path) -> None:
    (script,) = _blocks("bash")
    commands = [line for line in script.splitlines() if line.startswith("curl")]
    assert len(commands) == 2
    host = server.url.removeprefix("http://")
    answers = []
    for command in commands:
        # the README's python one-liner would overwrite the chair view with random points
        done = subprocess.run(
            command.replace("localhost:8000", host),
            shell=True,
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        )
        answers.append(json.loads(done.stdout))
    assert answers[0] == {"status": "ready"}
    assert answers[1]["model_id"].startswith("proc-") and len(answers[1]["pose"]) == 4
