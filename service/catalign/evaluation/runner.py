"""``catalign evaluate``: build both settings from the shared chairs or tables, run a method,
report."""

from __future__ import annotations

import json
import platform
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from catalign.data.shapes import SharedChairs
from catalign.data.views import WORLD_UP
from catalign.evaluation.protocol import (
    Setting,
    ViewMode,
    ViewSource,
    build_cases,
    frames_of,
    metric_shapes,
    run_cases,
    symmetries_of,
)
from catalign.evaluation.report import format_table, summarise
from catalign.geometry.se3 import axis_angle
from catalign.registration.config import EngineConfig
from catalign.registration.methods import build_registrar


@dataclass(frozen=True)
class EvaluationConfig:
    """What an evaluation run measures; stored with its results."""

    method: str = "fpfh"
    settings: tuple[Setting, ...] = ("same", "cross")
    views: int = 2
    source: ViewSource = "single"
    max_shapes: int | None = None
    seed: int = 0
    pose_mode: ViewMode = "upright"
    model_dir: Path | None = None
    up_prior: bool = True
    up_error_deg: float = 0.0
    floor: bool = False
    table: bool = False
    engine: EngineConfig | None = None
    category: str = "chair"


def evaluate(config: EvaluationConfig, chairs: SharedChairs) -> dict[str, Any]:
    """Run ``config.method`` on every setting; return the table rows and per-case details.

    ``chairs`` are the shared shapes of ``config.category`` (:class:`SharedChairs` or
    :class:`~catalign.data.shapes.SharedTables`), observed and in the library alike.

    ``max_shapes`` caps the number of observed validation shapes and the size of each library
    (the first ids in sorted order), for quick runs. ``up_prior`` tells the method that world
    +Z is up (true of upright observations; in ``so3`` and ``turned`` modes it is a wrong
    prior), tilted by ``up_error_deg`` (:func:`given_up`). ``floor`` keeps a ring of floor
    around every observed chair (the scene turned at random in so3); ``table`` pushes it under
    a table that hides what lies beneath its top. ``source`` is ``single`` (one depth frame per
    view) or ``fused`` (a reconstruction; see :mod:`catalign.evaluation.protocol`).
    """
    up = given_up(config.up_error_deg) if config.up_prior else None
    registrar = build_registrar(config.method, config.model_dir, up, config.engine)
    val_ids = _first(chairs.ids("val"), config.max_shapes)
    train_ids = _first(chairs.ids("train"), config.max_shapes)
    observed = metric_shapes(chairs, val_ids)
    cases = build_cases(
        observed,
        config.views,
        config.seed,
        config.pose_mode,
        floor=config.floor,
        table=config.table,
        source=config.source,
    )
    libraries = {"same": observed, "cross": metric_shapes(chairs, train_ids)}
    symmetries = symmetries_of(observed)

    summaries = []
    for setting in config.settings:
        library = libraries[setting]
        outcomes = run_cases(
            registrar, library, cases, config.seed, label=setting, category=config.category
        )
        frames = frames_of(observed | library)
        summaries.append(summarise(outcomes, frames, setting, symmetries))
    rows = [s["row"] for s in summaries]
    return {
        "config": config.__dict__
        | {
            "settings": list(config.settings),
            "model_dir": str(config.model_dir or ""),
            "engine": _engine_in_effect(config),
        },
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": platform.machine(),
        "split": {"val": len(val_ids), "train": len(train_ids)},
        "rows": rows,
        "table": format_table(config.method, rows),
        "cases": {s["row"]["setting"]: s["cases"] for s in summaries},
    }


def given_up(error_deg: float) -> np.ndarray:
    """The up the method is told: world +Z tilted by ``error_deg`` about world +X, as an
    imprecise IMU's is. Every view's chair has a yaw of its own, so the error points a
    different way for each chair."""
    return axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(error_deg)) @ WORLD_UP


def write_report(report: dict[str, Any], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=float))


def _first(ids: Sequence[str], count: int | None) -> list[str]:
    return list(ids if count is None else ids[:count])


def _engine_in_effect(config: EvaluationConfig) -> dict[str, Any] | None:
    """The engine options the run used (the report's record of them): None for the classic
    baseline, which has no engine."""
    if config.method == "fpfh":
        return None
    return (config.engine or EngineConfig()).model_dump()
