"""The confidence calibrator: its signals, its file, and its refusal of a foreign file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from catalign.errors import ConfigError
from catalign.registration.decision.confidence import (
    MAX_MARGIN,
    SIGNALS,
    Calibrator,
    Evidence,
    Tree,
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


def _stump(signal: str, threshold: float, low: float, high: float) -> Tree:
    """A tree of one split: ``low`` where ``signal`` is at most ``threshold``, else ``high``."""
    return Tree(
        feature=np.array([SIGNALS.index(signal), -2, -2]),
        threshold=np.array([threshold, -2.0, -2.0]),
        left=np.array([1, -1, -1]),
        right=np.array([2, -1, -1]),
        value=np.array([0.0, low, high]),
    )


def _calibrator(*trees: Tree, baseline: float = 0.0) -> Calibrator:
    return Calibrator(baseline, 0.5, trees, card={"command": "test"})


def test_signals_cap_the_margins_and_name_every_input() -> None:
    signals = _evidence().signals()
    assert tuple(signals) == SIGNALS
    assert signals["heading_margin"] == MAX_MARGIN
    assert signals["log_keypoints"] == pytest.approx(np.log(2_000))


def test_the_probability_is_the_logistic_of_the_trees_sum() -> None:
    calibrator = _calibrator(
        _stump("score", 0.5, -2.0, 2.0), _stump("model_margin", 0.4, 1.0, -1.0), baseline=0.3
    )
    # score 0.5 is at its threshold and goes left (-2), as scikit-learn sends it; model_margin
    # 0.5 goes right (-1): 0.3 + 0.5 * (-3).
    logit = 0.3 + 0.5 * (-2.0 - 1.0)
    assert calibrator.probability(_evidence()) == pytest.approx(1 / (1 + np.exp(-logit)))
    assert calibrator.probability(_evidence(score=0.9)) > calibrator.probability(_evidence())
    assert 0.0 < _calibrator(_stump("score", 0.1, 0.0, 1e6)).probability(_evidence()) <= 1.0


def test_deeper_trees_route_each_row_to_its_own_leaf() -> None:
    # score <= 0.6 ? (fitness <= 0.5 ? 1 : 2) : 3
    tree = Tree(
        feature=np.array([SIGNALS.index("score"), SIGNALS.index("fitness"), -2, -2, -2]),
        threshold=np.array([0.6, 0.5, -2.0, -2.0, -2.0]),
        left=np.array([1, 2, -1, -1, -1]),
        right=np.array([4, 3, -1, -1, -1]),
        value=np.array([0.0, 0.0, 1.0, 2.0, 3.0]),
    )
    rows = np.array([_evidence(score=s).row() for s in (0.5, 0.9)] + [_evidence().row()])
    rows[2, SIGNALS.index("fitness")] = 0.2
    calibrator = _calibrator(tree)
    np.testing.assert_array_equal(calibrator.tree_sums(rows), [2.0, 3.0, 1.0])
    # With a stump beside it, each row adds the stump's leaf: the trees are walked together.
    both = _calibrator(tree, _stump("covered", 0.5, 10.0, 20.0))
    np.testing.assert_array_equal(both.tree_sums(rows), [22.0, 23.0, 21.0])


def test_a_saved_calibrator_loads_and_gives_the_same_probabilities(tmp_path: Path) -> None:
    calibrator = _calibrator(_stump("score", 0.4, -1.0, 1.5), _stump("covered", 0.8, 0.5, -0.5))
    folder = tmp_path / "model" / "confidence"
    calibrator.save(folder)
    loaded = find_calibrator(tmp_path / "model")
    assert loaded is not None
    for evidence in (_evidence(), _evidence(score=0.2)):
        assert loaded.probability(evidence) == pytest.approx(calibrator.probability(evidence))
    assert loaded.card == {"command": "test"}
    assert find_calibrator(tmp_path / "elsewhere") is None


def test_a_calibrator_of_other_signals_is_refused_with_a_sentence(tmp_path: Path) -> None:
    folder = tmp_path / "confidence"
    path = _calibrator(_stump("score", 0.5, 0.0, 1.0)).save(folder)
    data = json.loads(path.read_text())
    data["signals"] = ["score", "fitness"]
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="catalign calibrate"):
        Calibrator.load(path)
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read"):
        Calibrator.load(path)
    data["signals"] = list(SIGNALS)
    tree = data["trees"][0]
    damaged = [
        {k: v for k, v in data.items() if k != "trees"},  # no trees at all
        data | {"trees": [tree | {"left": [1, -1]}]},  # arrays of different lengths
        data | {"trees": [tree | {"right": [7, -1, -1]}]},  # a child outside the tree
        data | {"trees": [tree | {"feature": [99, -2, -2]}]},  # a signal that does not exist
    ]
    for broken in damaged:
        path.write_text(json.dumps(broken))
        with pytest.raises(ConfigError, match="damaged"):
            Calibrator.load(path)
