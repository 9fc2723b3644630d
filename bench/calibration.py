"""How far the answers' ``confidence`` can be trusted: pooled over evaluation reports.

Reads the per-case JSON that ``catalign evaluate --out`` writes (several seeds of one pose
mode), pools each setting's cases, and reports the expected calibration error (10 bins), the
AUROC of right against wrong, what gating at confidence 0.8 keeps (the share right among the
kept answers, and their share of all), and, among answers turned from the truth by more than
45 degrees, the share whose right pose is among the alternatives. Prints a markdown table,
writes it to ``bench/results/calibration-upright.md`` (``--out``) and draws the reliability
diagram (confidence bins against the share right) to ``docs/reliability.png``.

    .venv/bin/python bench/calibration.py docs/results/evaluate-learned-upright-seed{0,1}.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from _report import publish

from catalign.evaluation.metrics import reliability_bins
from catalign.evaluation.report import confidence_columns

matplotlib.use("Agg")
import matplotlib.pyplot as plt

RESULTS = Path(__file__).parent / "results" / "calibration-upright.md"
DIAGRAM = Path(__file__).parents[1] / "docs" / "reliability.png"
COLUMNS = ("ECE", "AUROC", "conf>=0.8 right", "conf>=0.8 share", "turns rescued")


def pooled(reports: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Each setting's cases over every report."""
    cases: dict[str, list[dict[str, Any]]] = {}
    for report in reports:
        for setting, rows in report["cases"].items():
            cases.setdefault(setting, []).extend(rows)
    return cases


def reliability(cases: list[dict[str, Any]]) -> list[tuple[float, float, int]]:
    """The reliability diagram's points of ``cases`` (a refused view: confidence 0, wrong)."""
    p = np.array([c.get("confidence") or 0.0 for c in cases])
    right = np.array([bool(c.get("right")) for c in cases])
    return reliability_bins(p, right)


def draw(by_setting: dict[str, list[dict[str, Any]]], title: str, path: Path) -> None:
    """The reliability diagram: one line per setting, marker area by the bin's count."""
    figure, axes = plt.subplots(figsize=(4.5, 4.5), dpi=120)
    axes.plot([0, 1], [0, 1], color="grey", linestyle="--", linewidth=1, label="calibrated")
    for setting, cases in by_setting.items():
        points = reliability(cases)
        x, y, n = (np.array(v) for v in zip(*points, strict=True))
        axes.plot(x, y, marker="o", label=f"{setting} ({len(cases)} views)")
        axes.scatter(x, y, s=8 * n, alpha=0.3)
    axes.set_xlabel("confidence")
    axes.set_ylabel("share right (RRE<10 and RTE<5 cm)")
    axes.set_xlim(0, 1)
    axes.set_ylim(0, 1)
    axes.set_title(title, fontsize=9)
    axes.legend(loc="upper left", fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reports", type=Path, nargs="+", help="catalign evaluate JSON reports")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--diagram", type=Path, default=DIAGRAM)
    parser.add_argument("--title", default="reliability", help="The diagram's title.")
    args = parser.parse_args()
    reports = [json.loads(path.read_text()) for path in args.reports]
    by_setting = pooled(reports)
    names = ", ".join(path.name for path in args.reports)
    lines = [
        f"Confidence, pooled over {names}.",
        "",
        "| setting | views | right % | " + " | ".join(COLUMNS) + " |",
        "|---|---|---|" + "---|" * len(COLUMNS),
    ]
    for setting, cases in by_setting.items():
        columns = confidence_columns(cases)
        right = np.mean([bool(c.get("right")) for c in cases]) * 100
        cells = [
            "n/a"
            if columns[c] is None
            else f"{columns[c]:.3f}"
            if c in ("ECE", "AUROC")
            else f"{columns[c]:.1f}"
            for c in COLUMNS
        ]
        lines.append(f"| {setting} | {len(cases)} | {right:.1f} | " + " | ".join(cells) + " |")
    publish("\n".join(lines) + "\n", args.out)
    draw(by_setting, args.title, args.diagram)
    print(f"reliability diagram written to {args.diagram}")


if __name__ == "__main__":
    main()
