"""Kinds of calibrator compared on the same validation answers.

Every calibrator is fitted on the same samples (the answers on views of the training chairs
that ``catalign calibrate`` saves beside the calibrator it fits, ``samples.npz``) and scored on
the answers of ``catalign evaluate`` reports, read back from the evidence each report keeps of
its answers: the answers stay those of the engine that wrote the reports, only the confidence
read from their evidence changes. Per report group (seeds 0 and 1 pooled, seed 2, seed 3), pose
mode and setting: ECE (10 bins) / AUROC / the share right among answers with confidence >= 0.8
/ their share of all. Writes ``bench/results/calibrators.md``.

    .venv/bin/python bench/calibrators.py --samples runs/confidence-frame/samples.npz
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _report import publish

from catalign.evaluation.metrics import auroc, expected_calibration_error
from catalign.registration.decision.confidence import SIGNALS
from catalign.training.calibration import Samples, fit

RESULTS = Path(__file__).parent / "results" / "calibrators.md"
REPORTS = Path(__file__).parents[1] / "docs" / "results"
GROUPS = {"seeds 0 and 1": (0, 1), "seed 2": (2,), "seed 3": (3,)}

Scorer = Callable[[np.ndarray], np.ndarray]


def logistic(rows: np.ndarray, right: np.ndarray) -> Scorer:
    """A logistic regression on standardised signals (scikit-learn's defaults)."""
    from sklearn.linear_model import LogisticRegression

    mean, scale = rows.mean(axis=0), rows.std(axis=0)
    scale[scale < 1e-9] = 1.0
    model = LogisticRegression(max_iter=2_000).fit((rows - mean) / scale, right)
    return lambda x: model.predict_proba((x - mean) / scale)[:, 1]


def answers(mode: str, setting: str, seeds: tuple[int, ...]) -> tuple[list, np.ndarray]:
    """The winners' evidence rows (None for a refused view) and whether each is right."""
    rows, right = [], []
    for seed in seeds:
        report = json.loads((REPORTS / f"evaluate-learned-{mode}-seed{seed}.json").read_text())
        for case in report["cases"][setting]:
            evidence = case.get("evidence")
            rows.append(None if evidence is None else [evidence[name] for name in SIGNALS])
            right.append(bool(case.get("right")))
    return rows, np.array(right)


def quality(scorer: Scorer, rows: list, right: np.ndarray) -> tuple[float, float, str]:
    """ECE, AUROC and the table cell (with what gating at 0.8 keeps); a refused view is a
    wrong answer with confidence 0."""
    answered = [i for i, row in enumerate(rows) if row is not None]
    p = np.zeros(len(rows))
    p[answered] = scorer(np.array([rows[i] for i in answered]))
    ece, area, gate = expected_calibration_error(p, right), auroc(p, right), p >= 0.8
    kept = f"{100 * right[gate].mean():.0f}" if gate.any() else "-"
    return ece, area, f"{ece:.3f} / {area:.3f} / {kept} / {100 * gate.mean():.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    samples = Samples.load(args.samples)
    rows, right = samples.matrix(), np.array(samples.right, dtype=bool)
    kinds: dict[str, Scorer] = {
        "logistic regression": logistic(rows, right),
        "trees of 8 leaves, any depth": fit(samples, max_depth=None).probabilities,
        "trees, leaves of any size": fit(samples, min_samples_leaf=1).probabilities,
        "trees (shipped)": fit(samples).probabilities,
    }
    names = list(kinds)
    lines = [
        "# Kinds of calibrator on the same validation answers",
        "",
        f"Fitted on {len(rows)} answers ({args.samples}); scored on the winners of "
        "`docs/results/evaluate-learned-*-seed*.json`. Each cell: ECE / AUROC / % right among "
        "conf >= 0.8 / % of views with conf >= 0.8.",
        "",
        "| views | mode | setting | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    means: dict[str, list[tuple[float, float]]] = {name: [] for name in names}
    for group, seeds in GROUPS.items():
        for mode in ("upright", "so3"):
            for setting in ("same", "cross"):
                found, labels = answers(mode, setting, seeds)
                scored = [quality(kinds[name], found, labels) for name in names]
                for name, (ece, area, _) in zip(names, scored, strict=True):
                    means[name].append((ece, area))
                cells = " | ".join(text for _, _, text in scored)
                lines.append(f"| {group} | {mode} | {setting} | {cells} |")
    lines += ["", "Mean over the rows (ECE / AUROC):", ""]
    lines += [
        f"* {name}: {np.mean(v, axis=0)[0]:.3f} / {np.mean(v, axis=0)[1]:.3f}"
        for name, v in means.items()
    ]
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
