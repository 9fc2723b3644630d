"""The training commands refuse a bad option with one sentence naming it, before any work."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from catalign.cli import app

runner = CliRunner()


@pytest.mark.parametrize(
    ("arguments", "sentence"),
    [
        (["train-orientation", "--up-frame", "sideways"], "error: --up-frame: Input should be"),
        (["train-orientation", "--networks", "legs"], "error: --networks: Input should be"),
        (["train-orientation", "--so3-share", "1.5"], "error: --so3-share: Input should be"),
        (
            ["train-orientation", "--networks", "up"],
            "error: networks=up trains one network: the other needs init_from",
        ),
        (["train", "--curriculum", "backwards"], "error: --curriculum:"),
        (["train-orientation", "--category", "sofa"], "no shared shapes of category 'sofa'"),
        (["train-orientation", "--category", "Big Sofa"], "error: --category: String should"),
        (["calibrate", "--category", "sofa"], "no shared shapes of category 'sofa'"),
    ],
)
def test_a_refused_training_option_is_one_sentence(
    tmp_path: Path, arguments: list[str], sentence: str
) -> None:
    out = tmp_path / "run"
    result = runner.invoke(app, [*arguments, "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert sentence in result.output
    assert "Traceback" not in result.output
    assert not out.exists()
