"""Confidence: the probability that an answer is right, from evidence the engine already has.

"Right" is the evaluation's criterion: within 10 degrees and 5 cm of the truth in the
category-level metric (:mod:`catalign.evaluation.metrics`). No single statistic tells a right
answer from a quarter turn or a near-twin's pose (fitness does not), but together they do: how
much of the query the pose explains and how much of the model it covers, how far ahead it is of
the best pose of another heading and of another model, whether ``up`` was given, how many key
points the view has. A logistic regression on these :class:`Evidence` signals, fitted on views
of the *training* chairs (``catalign calibrate``, :mod:`catalign.training.calibration`), turns
them into a probability; it is stored as JSON beside the weights (``confidence/``), and applying
it takes a dot product.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from catalign.errors import ConfigError

CALIBRATOR_FILE = "calibrator.json"
FORMAT_VERSION = 2
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
        """The regression's inputs in :data:`SIGNALS` order: margins capped, the key points
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
        """The regression's inputs, by name."""
        return dict(zip(SIGNALS, self.row(), strict=True))


@dataclass(frozen=True)
class Calibrator:
    """A fitted logistic regression over standardised :data:`SIGNALS`.

    ``card`` records how it was fitted (command, data, counts, in-sample quality)."""

    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    intercept: float
    card: dict[str, Any]

    def probability(self, evidence: Evidence) -> float:
        """The probability that the answer ``evidence`` describes is right."""
        return float(self.probabilities(np.array([evidence.row()]))[0])

    def probabilities(self, rows: np.ndarray) -> np.ndarray:
        """The probability of each row of :data:`SIGNALS` values."""
        logits = ((rows - self.mean) / self.scale) @ self.coef + self.intercept
        return 1.0 / (1.0 + np.exp(-np.clip(logits, -50.0, 50.0)))

    def save(self, folder: Path) -> Path:
        """Write ``folder/calibrator.json``; its path."""
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / CALIBRATOR_FILE
        data = {
            "format_version": FORMAT_VERSION,
            "signals": list(SIGNALS),
            "mean": self.mean.tolist(),
            "scale": self.scale.tolist(),
            "coef": self.coef.tolist(),
            "intercept": self.intercept,
            "card": self.card,
        }
        path.write_text(json.dumps(data, indent=2) + "\n")
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
                f"the confidence calibrator {path} was fitted on other signals; fit it again "
                "with `catalign calibrate`"
            )
        return cls(
            mean=np.asarray(data["mean"], dtype=np.float64),
            scale=np.asarray(data["scale"], dtype=np.float64),
            coef=np.asarray(data["coef"], dtype=np.float64),
            intercept=float(data["intercept"]),
            card=data.get("card", {}),
        )


def find_calibrator(model_dir: Path) -> Calibrator | None:
    """The calibrator stored with the weights in ``model_dir/confidence/``, if there is one."""
    path = model_dir / "confidence" / CALIBRATOR_FILE
    return Calibrator.load(path) if path.is_file() else None
