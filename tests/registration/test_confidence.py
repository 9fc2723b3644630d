"""The confidence calibrator: its signals, its file, and its refusal of a foreign file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from catalign.errors import ConfigError
from catalign.registration.confidence import (
    MAX_MARGIN,
    SIGNALS,
    Calibrator,
    Evidence,
    find_calibrator,
)


def _evidence(score: float = 0.5, model_margin: float = 0.5) -> Evidence:
    return Evidence(
        score=score,
        explained=0.7,
        covered=0.7,
        heading_margin=9.0,
        model_margin=model_margin,
        fitness=0.8,
        rmse=0.5,
        inlier_ratio=0.8,
        span=0.9,
        up_given=True,
        up_belief=1.0,
        keypoints=2_000,
    )


def _calibrator(coef: dict[str, float], intercept: float = 0.0) -> Calibrator:
    n = len(SIGNALS)
    return Calibrator(
        mean=np.zeros(n),
        scale=np.ones(n),
        coef=np.array([coef.get(name, 0.0) for name in SIGNALS]),
        intercept=intercept,
        card={"command": "test"},
    )


def test_signals_cap_the_margins_and_name_every_input() -> None:
    signals = _evidence().signals()
    assert tuple(signals) == SIGNALS
    assert signals["heading_margin"] == MAX_MARGIN
    assert signals["log_keypoints"] == pytest.approx(np.log(2_000))


def test_the_probability_is_the_logistic_of_the_weighted_signals() -> None:
    calibrator = _calibrator({"score": 4.0, "model_margin": -2.0}, intercept=-1.0)
    logit = 4.0 * 0.5 - 2.0 * 0.5 - 1.0
    assert calibrator.probability(_evidence()) == pytest.approx(1 / (1 + np.exp(-logit)))
    assert calibrator.probability(_evidence(score=0.9)) > calibrator.probability(_evidence())
    assert 0.0 < _calibrator({"score": 1e6}).probability(_evidence()) <= 1.0


def test_a_saved_calibrator_loads_and_gives_the_same_probabilities(tmp_path: Path) -> None:
    calibrator = _calibrator({"score": 3.0, "covered": 1.5}, intercept=-0.5)
    folder = tmp_path / "model" / "confidence"
    calibrator.save(folder)
    loaded = find_calibrator(tmp_path / "model")
    assert loaded is not None
    assert loaded.probability(_evidence()) == pytest.approx(calibrator.probability(_evidence()))
    assert loaded.card == {"command": "test"}
    assert find_calibrator(tmp_path / "elsewhere") is None


def test_a_calibrator_of_other_signals_is_refused_with_a_sentence(tmp_path: Path) -> None:
    folder = tmp_path / "confidence"
    path = _calibrator({}).save(folder)
    data = json.loads(path.read_text())
    data["signals"] = ["score", "fitness"]
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="catalign calibrate"):
        Calibrator.load(path)
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read"):
        Calibrator.load(path)
