"""Turn case outcomes into the paper's table: success rates, MatchAcc, retrieval, the
orientation proposals' quality (share of views whose true up and heading were proposed), and
timing."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from catalign.evaluation.metrics import (
    TURNED_DEG,
    PoseError,
    auroc,
    canonical_pose_error,
    expected_calibration_error,
    gated,
    is_right,
    match_accuracy,
    proposal_hits,
    success_rates,
)
from catalign.evaluation.protocol import CaseOutcome
from catalign.geometry.ncc import NCCFrame
from catalign.geometry.symmetry import NO_SYMMETRY, YawSymmetry
from catalign.registration.decision.confidence import Evidence

# A refused view (too little of the chair in sight) fails every threshold.
REFUSED = PoseError(rre_deg=180.0, rte_m=float("inf"))
COLUMNS = (
    "RRE<10",
    "RRE<20",
    "RRE<30",
    "RTE<5cm",
    "RTE<10cm",
    "MatchAcc",
    "top-1",
    "up@1",
    "up@3",
    "heading@1",
    "heading@2",
    "ECE",
    "AUROC",
    "conf>=0.8 right",
    "conf>=0.8 share",
    "turns rescued",
    "s/query median",
    "s/query p95",
)


def summarise(
    outcomes: Sequence[CaseOutcome],
    frames: dict[str, NCCFrame],
    setting: str,
    symmetries: Mapping[str, YawSymmetry] | None = None,
) -> dict[str, Any]:
    """One row of the table plus per-case details, for one setting.

    ``frames`` holds the NCC frame of every shape involved (observed and library),
    ``symmetries`` the observed shapes' symmetries (rotation errors are to the nearest
    equivalent pose; none when absent).
    """
    symmetries = symmetries or {}
    errors, accuracies, cases, hits = [], [], [], []
    for outcome in outcomes:
        case, result = outcome.case, outcome.result
        if result is None:
            errors.append(REFUSED)
            cases.append({"case": case.case_id, "model_id": None, "refused": outcome.refused})
            continue
        model_frame, observed_frame = frames[result.model_id], frames[case.shape_id]
        symmetry = symmetries.get(case.shape_id, NO_SYMMETRY)
        error = canonical_pose_error(result.pose, model_frame, case.pose, observed_frame, symmetry)
        errors.append(error)
        accuracy = None
        if result.correspondences is not None:
            accuracy = match_accuracy(
                *result.correspondences, model_frame, case.pose, observed_frame
            )
            accuracies.append(accuracy)
        hit = proposal_hits(result.orientations, case.pose[:3, :3], symmetry)
        hits.append(hit)
        alternatives = [
            {
                "model_id": other.model_id,
                "right": is_right(
                    canonical_pose_error(
                        other.pose, frames[other.model_id], case.pose, observed_frame, symmetry
                    )
                ),
                "confidence": other.confidence,
                "evidence": _evidence(other.evidence),
            }
            for other in result.alternatives
        ]
        cases.append(
            {
                "case": case.case_id,
                "model_id": result.model_id,
                "rre_deg": error.rre_deg,
                "rte_m": error.rte_m,
                "match_acc": accuracy,
                "fitness": result.fitness,
                "confidence": result.confidence,
                "evidence": _evidence(result.evidence),
                "right": is_right(error),
                "alternatives": alternatives,
                "seconds": outcome.seconds,
            }
            | hit
        )
    seconds = np.array([o.seconds for o in outcomes])
    row: dict[str, Any] = {"setting": setting, "cases": len(outcomes)} | success_rates(errors)
    row["refused"] = sum(o.result is None for o in outcomes)
    row["MatchAcc"] = float(np.mean(accuracies) * 100) if accuracies else None
    row["top-1"] = (
        float(
            np.mean(
                [o.result is not None and o.result.model_id == o.case.shape_id for o in outcomes]
            )
            * 100
        )
        if setting == "same"
        else None
    )
    for column in ("up@1", "up@3", "heading@1", "heading@2"):
        known = [h[column] for h in hits if h[column] is not None]
        row[column] = float(np.mean(known) * 100) if known else None
    row |= confidence_columns(cases)
    row["s/query median"] = float(np.median(seconds))
    row["s/query p95"] = float(np.percentile(seconds, 95))
    return {"row": row, "cases": cases}


def _evidence(evidence: Evidence | None) -> dict[str, float] | None:
    """An answer's confidence signals, so another calibrator can be scored on the report's
    answers without registering them again."""
    return None if evidence is None else evidence.signals()


def confidence_columns(cases: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """How well ``confidence`` tells right answers from wrong ones (a refused view counts as
    a wrong answer with confidence 0), what gating at 0.8 keeps, and the share of answers
    turned from the truth (a quarter or half turn) whose right pose is among the
    alternatives. None where the answers carry no confidence."""
    if not cases or any(c.get("model_id") and c.get("confidence") is None for c in cases):
        return dict.fromkeys(
            ("ECE", "AUROC", "conf>=0.8 right", "conf>=0.8 share", "turns rescued")
        )
    p = np.array([c.get("confidence") or 0.0 for c in cases])
    right = np.array([bool(c.get("right")) for c in cases])
    gate = gated(p, right)
    turned = [c for c in cases if c.get("model_id") and c["rre_deg"] > TURNED_DEG]
    rescued = [any(a["right"] for a in c["alternatives"]) for c in turned]
    return {
        "ECE": expected_calibration_error(p, right),
        "AUROC": auroc(p, right),
        "conf>=0.8 right": gate["precision"],
        "conf>=0.8 share": gate["coverage"],
        "turns rescued": float(np.mean(rescued) * 100) if rescued else None,
    }


def format_table(method: str, rows: Sequence[dict[str, Any]]) -> str:
    """A markdown table: one line per setting, percentages with one decimal."""
    header = ["method", "setting", "cases", *COLUMNS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        cells = [method, row["setting"], str(row["cases"])]
        for column in COLUMNS:
            value = row.get(column)
            if value is None:
                cells.append("n/a")
            elif column.startswith("s/") or column in ("ECE", "AUROC"):
                cells.append(f"{value:.3f}")
            else:
                cells.append(f"{value:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
