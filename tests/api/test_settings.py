"""Settings come from CATALIGN_* variables, flags override them, bad values are refused."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from contextlib import AbstractContextManager, closing
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import pytest
from pydantic import ValidationError
from typer.testing import CliRunner

from catalign import threads
from catalign.api.settings import DEFAULT_MODEL_DIR, ServiceSettings
from catalign.cli import app
from catalign.registration.config import EngineConfig
from catalign.threads import cgroup_cpu_limit
from catalign_client import Client

if TYPE_CHECKING:
    from tests.api.conftest import ServerProcess, View


def test_environment_is_read_and_keywords_override_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CATALIGN_PORT", "9001")
    monkeypatch.setenv("CATALIGN_MAX_POINTS", "1234")
    monkeypatch.setenv("CATALIGN_READ_ONLY", "true")
    settings = ServiceSettings(port=9002)
    assert (settings.port, settings.max_points, settings.read_only) == (9002, 1234, True)


def test_engine_options_come_from_nested_variables(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CATALIGN_ENGINE__TOP_K", "4")
    monkeypatch.setenv("CATALIGN_ENGINE__MATCH__MODEL_POINTS", "none")
    monkeypatch.setenv("CATALIGN_ENGINE__FLOOR__MAX_TILT_DEG", "8")
    monkeypatch.setenv("CATALIGN_ENGINE__SWEEP_MODELS", "3")  # a flat name of earlier releases
    engine = ServiceSettings().engine
    assert (engine.top_k, engine.match.model_points, engine.floor.max_tilt_deg) == (4, None, 8.0)
    assert engine.sweep.models == 3
    assert engine.match.query_points == EngineConfig().match.query_points
    monkeypatch.setenv("CATALIGN_ENGINE__SWEEP__MODEL", "4")
    with pytest.raises(ValidationError, match="model"):
        ServiceSettings()
    monkeypatch.delenv("CATALIGN_ENGINE__SWEEP__MODEL")
    monkeypatch.setenv("CATALIGN_ENGINE__TOPK", "4")
    with pytest.raises(ValidationError, match="topk"):
        ServiceSettings()


def test_a_renamed_variable_is_refused_with_its_new_name(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CATALIGN_TOP_K", "4")
    with pytest.raises(ValidationError, match="CATALIGN_TOP_K is now CATALIGN_ENGINE__TOP_K"):
        ServiceSettings()


def test_defaults_serve_model_store() -> None:
    from catalign.features.extractor import DEFAULT_MODEL_DIR as EXTRACTOR_DEFAULT

    settings = ServiceSettings()
    assert DEFAULT_MODEL_DIR == EXTRACTOR_DEFAULT
    assert settings.library == EXTRACTOR_DEFAULT / "library"
    assert (settings.host, settings.port, settings.grpc_port) == ("127.0.0.1", 8000, 50051)
    assert settings.max_body_bytes == 64 * 2**20 and settings.max_points == 500_000


@pytest.mark.parametrize(
    "bad",
    [
        {"port": 0},
        {"port": 70000},
        {"grpc_port": -1},
        {"port": 8000, "grpc_port": 8000},
        {"workers": 0},
        {"queue": -1},
        {"api_key": "short"},
        {"api_key": " padded-key "},
        {"host": "http://localhost"},
        {"max_points": 0},
        {"log_level": "loud"},
        {"unknown": 1},
    ],
)
def test_bad_values_are_refused(bad: dict) -> None:
    with pytest.raises(ValidationError):
        ServiceSettings(**bad)


def test_serve_refuses_bad_flags_in_one_sentence(tmp_path: Path) -> None:
    runner = CliRunner()
    bad_port = runner.invoke(app, ["serve", "--port", "0"])
    assert bad_port.exit_code == 2 and "--port" in bad_port.output
    no_weights = runner.invoke(app, ["serve", "--model-dir", str(tmp_path)])
    assert no_weights.exit_code == 2 and "no trained weights" in no_weights.output
    typo = runner.invoke(app, ["serve", "--engine", "topk=4"])
    assert typo.exit_code == 2 and "unknown engine option 'topk'" in typo.output
    assert "Traceback" not in typo.output


def test_serve_refuses_a_library_of_other_weights_in_one_sentence(tmp_path: Path) -> None:
    # other feature weights (a card of another sha256): refused before start-up, with the
    # command that rebuilds the library
    other = tmp_path / "other"
    other.mkdir()
    (other / "model.safetensors").symlink_to(DEFAULT_MODEL_DIR / "model.safetensors")
    card = json.loads((DEFAULT_MODEL_DIR / "model_card.json").read_text())
    (other / "model_card.json").write_text(json.dumps({**card, "sha256": "0" * 64}))
    library = DEFAULT_MODEL_DIR / "library"
    flags = ["--model-dir", str(other), "--library", str(library)]
    result = CliRunner().invoke(app, ["serve", *flags])
    assert result.exit_code == 2, result.output
    assert "built with feature extractor" in result.output
    assert "catalign library build" in result.output and "Traceback" not in result.output


def test_serve_refuses_a_library_of_other_retrieval_encoders_naming_redescribe(
    tmp_path: Path,
) -> None:
    # the shipped weights without their retrieval encoders: the features match, the library's
    # descriptors are the encoders', so it is refused with the command that describes it again
    for name in ("model.safetensors", "model_card.json"):
        (tmp_path / name).symlink_to(DEFAULT_MODEL_DIR / name)
    library = DEFAULT_MODEL_DIR / "library"
    result = CliRunner().invoke(
        app, ["serve", "--model-dir", str(tmp_path), "--library", str(library)]
    )
    assert result.exit_code == 2, result.output
    assert "shortlisted by other retrieval encoders" in result.output
    assert f"catalign library redescribe {library}" in result.output.replace("\n", "")
    assert "Traceback" not in result.output


def test_serve_engine_flags_go_over_the_variables_field_by_field(
    serve_process: Callable[..., AbstractContextManager[ServerProcess]], library_dir: Path
) -> None:
    flags = ("--engine", "icp.poses=2", "--engine", "decision.alternatives=1")
    environment = {"CATALIGN_ENGINE__TOP_K": "4", "CATALIGN_ENGINE__ICP__POSES": "5"}
    with serve_process(library_dir, *flags, env=environment) as server:
        engine = httpx.get(f"{server.url}/info", timeout=10).json()["engine"]
    assert (engine["top_k"], engine["icp"]["poses"], engine["decision"]["alternatives"]) == (
        4,
        2,
        1,
    )
    assert engine["match"] == EngineConfig().match.model_dump()


def test_a_librarys_engine_options_apply_under_the_services(
    serve_process: Callable[..., AbstractContextManager[ServerProcess]],
    library_copy: Path,
    views: Callable[..., View],
) -> None:
    options = ("--engine", "decision.alternatives=0", "--engine", "top_k=2", "--engine", "refine=4")
    configured = CliRunner().invoke(app, ["library", "configure", str(library_copy), *options])
    assert configured.exit_code == 0, configured.output
    environment = {"CATALIGN_ENGINE__TOP_K": "3"}
    with serve_process(library_copy, "--engine", "icp.poses=2", env=environment) as server:
        info = httpx.get(f"{server.url}/info", timeout=10).json()
        with Client(server.url, timeout=120) as client:
            result = client.align(views(seed=1).points, up=(0, 0, 1), seed=3)
    # stored as a tree, a flat name of earlier releases (refine) in its place
    stored = {"decision": {"alternatives": 0}, "top_k": 2, "icp": {"poses": 4}}
    assert info["library"]["engine"] == stored
    # the variable and the flag win over the library, the library over the defaults
    engine = info["engine"]
    assert (engine["top_k"], engine["icp"]["poses"], engine["decision"]["alternatives"]) == (
        3,
        2,
        0,
    )
    assert engine["match"] == EngineConfig().match.model_dump()
    # the worker processes run with them too: no alternatives
    assert result.model_id == "proc-0001" and len(result.alternatives) == 0


def test_serve_refuses_a_library_whose_engine_option_is_bad_in_one_sentence(
    library_copy: Path,
) -> None:
    catalogue = sqlite3.connect(library_copy / "catalogue.sqlite")
    with closing(catalogue), catalogue:  # edited by hand: `catalign library configure` refuses it
        catalogue.execute("UPDATE library SET engine = ?", (json.dumps({"top_k": 0}),))
    result = CliRunner().invoke(app, ["serve", "--library", str(library_copy)])
    assert result.exit_code == 2
    assert f"the library {library_copy} sets engine option top_k" in result.stderr
    assert "catalign library configure" in result.stderr and "Traceback" not in result.output


def test_the_api_key_comes_from_the_environment_or_a_file(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("CATALIGN_API_KEY", "from-the-environment")
    assert ServiceSettings().api_key.get_secret_value() == "from-the-environment"
    monkeypatch.delenv("CATALIGN_API_KEY")
    key_file = tmp_path / "key"
    key_file.write_text("from-a-file-123\nsecond line ignored\n")
    monkeypatch.setenv("CATALIGN_API_KEY_FILE", str(key_file))
    assert ServiceSettings().api_key.get_secret_value() == "from-a-file-123"
    with pytest.raises(ValidationError, match="not both"):
        ServiceSettings(api_key="another-key-456")
    key_file.write_text("short\n")
    with pytest.raises(ValidationError, match="at least 8"):
        ServiceSettings()


def test_serve_names_an_unreadable_key_file(tmp_path: Path) -> None:
    missing = tmp_path / "no-such-key"
    result = CliRunner().invoke(app, ["serve", "--api-key-file", str(missing)])
    assert result.exit_code == 2
    assert f"cannot read the API key file {missing}" in result.output


@pytest.mark.parametrize(
    ("variable", "value", "service"),
    [
        ("CATALIGN_PORT", "tcp://10.0.0.1:8000", "catalign"),
        ("CATALIGN_GRPC_PORT", "tcp://10.96.3.7:50051", "catalign-grpc"),
        ("CATALIGN_PORT", "udp://10.0.0.1:53", "catalign"),
    ],
)
def test_serve_refuses_a_service_link_variable_in_one_sentence(
    variable: str, value: str, service: str
) -> None:
    """A Service named ``catalign`` injects CATALIGN_PORT=tcp://...: named, with the way out."""
    result = CliRunner().invoke(app, ["serve"], env={variable: value})
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.output
    assert lines[0].startswith(f"error: {variable}={value} is a Kubernetes service-link variable")
    assert f"a Service named {service}" in lines[0]
    assert "`enableServiceLinks: false`" in lines[0] and "rename the Service" in lines[0]


def test_a_flag_overrides_a_service_link_variable(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        app,
        ["serve", "--port", "9000", "--model-dir", str(tmp_path)],
        env={"CATALIGN_PORT": "tcp://10.0.0.1:8000"},
    )
    assert result.exit_code == 2 and "no trained weights" in result.output  # got past settings


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        ({"cpu.max": "200000 100000\n"}, 2),  # a Kubernetes limit of 2 CPUs
        ({"cpu.max": "150000 100000\n"}, 2),  # 1.5 CPUs: rounded up
        ({"cpu.max": "50000 100000\n"}, 1),
        ({"cpu.max": "max 100000\n"}, None),  # cgroup v2, unlimited
        ({"cpu/cpu.cfs_quota_us": "300000\n", "cpu/cpu.cfs_period_us": "100000\n"}, 3),
        ({"cpu,cpuacct/cpu.cfs_quota_us": "25000", "cpu,cpuacct/cpu.cfs_period_us": "50000"}, 1),
        ({"cpu/cpu.cfs_quota_us": "-1\n", "cpu/cpu.cfs_period_us": "100000\n"}, None),
        ({"cpu.max": "garbage\n"}, None),
        ({}, None),  # no cgroup CPU controller (not Linux, or not mounted)
    ],
)
def test_the_cgroup_cpu_limit_is_read_from_v2_or_v1_files(
    tmp_path: Path, files: dict[str, str], expected: int | None
) -> None:
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert cgroup_cpu_limit(tmp_path) == expected


def test_the_default_threads_per_worker_honour_the_cpu_limit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A container limited to 2 CPUs on a 64-core node: 1 thread for each of 2 workers."""
    monkeypatch.setattr(threads.os, "sched_getaffinity", lambda pid: set(range(64)))
    monkeypatch.setattr(threads, "cgroup_cpu_limit", lambda: 2)
    assert threads.cores() == 2
    assert ServiceSettings(workers=2).worker_threads == 1
    assert ServiceSettings(workers=2, threads_per_worker=3).worker_threads == 3
    monkeypatch.setattr(threads, "cgroup_cpu_limit", lambda: 128)  # above the affinity
    assert threads.cores() == 64
    monkeypatch.setattr(threads, "cgroup_cpu_limit", lambda: None)  # no limit
    assert ServiceSettings(workers=4).worker_threads == 16
