"""Confidence: the probability that an answer is right, from evidence the engine already has.

"Right" is the evaluation's criterion: within 10 degrees and 5 cm of the truth in the
category-level metric (:mod:`catalign.evaluation.metrics`). No single statistic tells a right
answer from a quarter turn or a near-twin's pose (fitness does not), but together they do: how
much of the query the pose explains and how much of the model it covers, how far ahead it is of
the best pose of another heading and of another model, whether ``up`` was given, how many key
points the view has. Gradient-boosted regression trees on these :class:`Evidence` signals,
fitted on views of the *training* chairs (``catalign calibrate``,
:mod:`catalign.training.calibration`), turn them into a probability. Trees, not a logistic
regression: whether an answer is right depends on the signals together (a high fitness is
worth less when the view spans little of the model), and on the validation views the trees
rank right answers above wrong ones better (``docs/evaluation.md``). They are stored as JSON
beside the weights (``confidence/``): applying them walks a few hundred small trees, with no
scikit-learn at query time.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from catalign.errors import ConfigError
from catalign.paths import CATEGORIES_DIR

CALIBRATOR_FILE = "calibrator.json"
# The calibrator's folder beside the feature weights it was fitted on.
CALIBRATION_DIR = "confidence"
FORMAT_VERSION = 3
# Margins are capped: an answer ten times behind another is as wrong as one twice behind.
MAX_MARGIN = 2.0
# A span over the model's extent past this is stray points, not more of the chair.
MAX_SPAN = 1.5
SIGNALS = (
    "score",
    "explained",
    "covered",
    "heading_margin",
    "model_margin",
    "fitness",
    "rmse",
    "inlier_ratio",
    "span",
    "up_given",
    "up_belief",
    "log_keypoints",
)


@dataclass(frozen=True)
class Evidence:
    """What the engine knows about one answer (the winner or an alternative).

    ``score`` is its verification score after ICP (weighed by the belief in its up and in its
    heading);
    ``explained`` and ``covered`` the two shares it is the product of; ``heading_margin`` and
    ``model_margin`` the best score of a pose of the same model turned another way, and of
    another model, over its own; ``fitness``, ``rmse`` (in ICP distances) and ``inlier_ratio``
    the ICP statistics of the final pose; ``span`` the smallest share, over the model's three
    axes, of the model's extent that the view spans under the final pose (a hidden side leaves
    the category-level centre uncertain); ``up_given`` and ``up_belief`` where its up came
    from; ``keypoints`` the query's key points.
    """

    score: float
    explained: float
    covered: float
    heading_margin: float
    model_margin: float
    fitness: float
    rmse: float
    inlier_ratio: float
    span: float
    up_given: bool
    up_belief: float
    keypoints: int

    def row(self) -> list[float]:
        """The calibrator's inputs in :data:`SIGNALS` order: margins capped, the key points
        on a log scale."""
        return [
            self.score,
            self.explained,
            self.covered,
            min(self.heading_margin, MAX_MARGIN),
            min(self.model_margin, MAX_MARGIN),
            self.fitness,
            self.rmse,
            self.inlier_ratio,
            min(self.span, MAX_SPAN),
            float(self.up_given),
            self.up_belief,
            math.log(max(self.keypoints, 1)),
        ]

    def signals(self) -> dict[str, float]:
        """The calibrator's inputs, by name."""
        return dict(zip(SIGNALS, self.row(), strict=True))


@dataclass(frozen=True)
class Tree:
    """One regression tree: its nodes as scikit-learn's ``tree_`` holds them (node 0 the root,
    a leaf's children -1; a row goes left where its ``feature`` is at most ``threshold``,
    compared in float32 as scikit-learn compares them)."""

    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    value: np.ndarray

    def to_json(self) -> dict[str, list]:
        return {name: getattr(self, name).tolist() for name in TREE_ARRAYS}

    @classmethod
    def from_json(cls, data: dict[str, list]) -> Tree:
        """A tree read back; ValueError when its nodes do not make one (a damaged file must
        fail when loaded, not in a query)."""
        arrays = {name: np.asarray(data[name], dtype=np.float64) for name in TREE_ARRAYS}
        if len({a.shape for a in arrays.values()}) != 1 or arrays["value"].ndim != 1:
            raise ValueError("a tree's node arrays differ in length")
        for name in ("feature", "left", "right"):
            arrays[name] = arrays[name].astype(np.int64)
        size, inner = len(arrays["value"]), arrays["left"] >= 0
        children = np.concatenate([arrays["left"][inner], arrays["right"][inner]])
        if size == 0 or np.any((children <= 0) | (children >= size)):
            raise ValueError("a tree's children point outside it")
        if np.any((arrays["feature"][inner] < 0) | (arrays["feature"][inner] >= len(SIGNALS))):
            raise ValueError("a tree splits on a signal that does not exist")
        return cls(**arrays)


TREE_ARRAYS = ("feature", "threshold", "left", "right", "value")


@dataclass(frozen=True)
class Calibrator:
    """Gradient-boosted trees over :data:`SIGNALS`: the log-odds of being right are
    ``baseline`` plus ``learning_rate`` times the sum of the trees' values.

    ``card`` records how it was fitted (command, data, counts, in-sample quality)."""

    baseline: float
    learning_rate: float
    trees: tuple[Tree, ...]
    card: dict[str, Any]

    def probability(self, evidence: Evidence) -> float:
        """The probability that the answer ``evidence`` describes is right."""
        return float(self.probabilities(np.array([evidence.row()]))[0])

    def probabilities(self, rows: np.ndarray) -> np.ndarray:
        """The probability of each row of :data:`SIGNALS` values."""
        logits = self.baseline + self.learning_rate * self.tree_sums(rows)
        return 1.0 / (1.0 + np.exp(-np.clip(logits, -50.0, 50.0)))

    def tree_sums(self, rows: np.ndarray) -> np.ndarray:
        """The sum over the trees of the leaf each row reaches: every tree walked at once, a
        level a step (a query reads a few answers' confidences; tree by tree it cost
        milliseconds)."""
        feature, threshold, left, right, value, roots = self._forest
        rows = np.asarray(rows, dtype=np.float32).reshape(-1, len(SIGNALS))
        node = np.broadcast_to(roots, (len(rows), len(roots))).copy()
        at_row = np.arange(len(rows))[:, None]
        inner = left[node] >= 0
        while inner.any():
            go_left = rows[at_row, feature[node]] <= threshold[node]
            node = np.where(inner, np.where(go_left, left[node], right[node]), node)
            inner = left[node] >= 0
        return value[node].sum(axis=1)

    @cached_property
    def _forest(self) -> tuple[np.ndarray, ...]:
        """The trees' nodes in one set of arrays (children numbered across trees) and each
        tree's root."""
        sizes = [len(tree.value) for tree in self.trees]
        roots = np.cumsum([0, *sizes[:-1]]).astype(np.int64)

        def children(name: str) -> np.ndarray:
            parts = [getattr(t, name) for t in self.trees]
            return np.concatenate(
                [np.where(p >= 0, p + r, -1) for p, r in zip(parts, roots, strict=True)]
            )

        feature = np.concatenate([np.maximum(t.feature, 0) for t in self.trees])
        threshold = np.concatenate([t.threshold for t in self.trees])
        value = np.concatenate([t.value for t in self.trees])
        return feature, threshold, children("left"), children("right"), value, roots

    def save(self, folder: Path) -> Path:
        """Write ``folder/calibrator.json``; its path."""
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / CALIBRATOR_FILE
        header = {
            "format_version": FORMAT_VERSION,
            "signals": list(SIGNALS),
            "baseline": self.baseline,
            "learning_rate": self.learning_rate,
            "card": self.card,
        }
        # The header indented for a reader, then one tree a line.
        trees = ",\n".join(f"    {json.dumps(tree.to_json())}" for tree in self.trees)
        text = json.dumps(header, indent=2)[:-2] + f',\n  "trees": [\n{trees}\n  ]\n}}\n'
        path.write_text(text)
        return path

    @classmethod
    def load(cls, path: Path) -> Calibrator:
        """Read a calibrator file; a clear error when it is not one this code can apply."""
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise ConfigError(f"cannot read the confidence calibrator {path}: {error}") from None
        if data.get("format_version") != FORMAT_VERSION or data.get("signals") != list(SIGNALS):
            raise ConfigError(
                f"the confidence calibrator {path} was fitted on other signals or by another "
                "version; fit it again with `catalign calibrate` (`--samples` refits from the "
                "samples beside it)"
            )
        try:
            trees = tuple(Tree.from_json(tree) for tree in data["trees"])
            baseline, rate = float(data["baseline"]), float(data["learning_rate"])
        except (KeyError, TypeError, ValueError) as error:
            raise ConfigError(f"the confidence calibrator {path} is damaged: {error}") from None
        return cls(baseline, rate, trees, card=data.get("card", {}))


def find_calibrator(model_dir: Path) -> Calibrator | None:
    """The calibrator stored with the weights in ``model_dir/confidence/``, if there is one."""
    path = model_dir / CALIBRATION_DIR / CALIBRATOR_FILE
    return Calibrator.load(path) if path.is_file() else None


def find_category_calibrators(model_dir: Path) -> dict[str, Calibrator]:
    """The calibrators fitted on one category's answers
    (``model_dir/categories/<name>/confidence/``), by category name."""
    pattern = f"*/{CALIBRATION_DIR}/{CALIBRATOR_FILE}"
    return {
        path.parent.parent.name: Calibrator.load(path)
        for path in sorted((model_dir / CATEGORIES_DIR).glob(pattern))
    }
