"""Settings come from CATALIGN_* variables, flags override them, bad values are refused."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError
from typer.testing import CliRunner

from catalign.api.settings import DEFAULT_MODEL_DIR, ServiceSettings
from catalign.cli import app
from catalign.registration.config import EngineConfig


def test_environment_is_read_and_keywords_override_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CATALIGN_PORT", "9001")
    monkeypatch.setenv("CATALIGN_MAX_POINTS", "1234")
    monkeypatch.setenv("CATALIGN_READ_ONLY", "true")
    settings = ServiceSettings(port=9002)
    assert (settings.port, settings.max_points, settings.read_only) == (9002, 1234, True)


def test_engine_options_come_from_nested_variables(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CATALIGN_ENGINE__TOP_K", "4")
    monkeypatch.setenv("CATALIGN_ENGINE__MODEL_POINTS", "none")
    settings = ServiceSettings()
    assert (settings.engine.top_k, settings.engine.model_points) == (4, None)
    assert settings.engine.match_points == EngineConfig().match_points
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
