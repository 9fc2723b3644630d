"""Speed against accuracy: the evaluation's test cases under several engine settings.

Each setting (``name=value`` :class:`~catalign.registration.config.EngineConfig` options by
their dotted names, comma-separated, ``none`` for None; ``default`` for none changed; an unknown
name or a bad value fails before anything runs) registers every test case of ``catalign
evaluate`` (both settings, every ``--seeds`` seed) through the same real library indexes, built
once, and is scored exactly as the evaluation scores it. The
per-query time is the engine's own (the sum of its stage timings), so the table compares
settings measured in one sitting on the same cases. Prints a markdown table and writes it to
``bench/results/tradeoff.md``; needs the shared chairs.

    .venv/bin/python bench/tradeoff.py [--seeds 0 1] [--model-dir DIR] \
        [--configs default match.keep_headings=2 match.query_points=1000,match.model_points=none]
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _report import load_average, publish

from catalign.data.shapes import SharedChairs
from catalign.data.views import WORLD_UP
from catalign.evaluation.protocol import (
    CaseOutcome,
    build_cases,
    frames_of,
    metric_shapes,
)
from catalign.evaluation.report import summarise
from catalign.features.extractor import LearnedExtractor
from catalign.registration.config import EngineConfig, parse_options
from catalign.registration.engine import Engine
from catalign.registration.indexed import IndexedRegistrar
from catalign.registration.results import LibraryShape
from catalign.threads import limit_threads

RESULTS = Path(__file__).parent / "results" / "tradeoff.md"
RATE_COLUMNS = ("RRE<10", "RRE<20", "RRE<30", "RTE<5cm", "RTE<10cm")
DEFAULT_CONFIGS = [
    "default",
    # 1,000 query key points against all of a model's
    "match.query_points=1000,match.model_points=none",
    "match.model_points=1500",
    "match.keep_headings=2",
    "match.heading_models=5",
]


def parse_config(text: str) -> EngineConfig:
    """``a=1,b=0.5,c=none`` as an engine configuration (``default``: the defaults); an unknown
    field or a bad value raises :class:`~catalign.errors.ConfigError`."""
    return parse_options([] if text == "default" else text.split(","))


def engine_ms(outcome: CaseOutcome) -> float:
    return sum(outcome.result.timings_ms.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--model-dir", type=Path, default=None)
    parser.add_argument("--chairs-dir", type=Path, default=None)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)  # as the server's workers run

    configs = {text: parse_config(text) for text in args.configs}  # a typo fails here, early
    chairs = SharedChairs(args.chairs_dir)
    extractor = LearnedExtractor(args.model_dir)
    observed = metric_shapes(chairs, chairs.ids("val"))
    libraries = {"same": observed, "cross": metric_shapes(chairs, chairs.ids("train"))}
    frames = frames_of(observed | libraries["cross"])
    registrars = {}
    for setting, shapes in libraries.items():
        registrar = IndexedRegistrar(extractor, name="learned")
        registrar.prepare([LibraryShape(i, s.points, s.mesh) for i, s in sorted(shapes.items())])
        registrars[setting] = registrar
    cases = {seed: build_cases(observed, args.views, seed) for seed in args.seeds}

    rows = []
    for text, config in configs.items():
        outcomes: dict[str, list[CaseOutcome]] = {"same": [], "cross": []}
        for setting, registrar in registrars.items():
            engine = Engine(extractor, registrar.engine.library, config=config)
            for seed, seed_cases in cases.items():
                for case in seed_cases:
                    result = engine.register(case.points, up=WORLD_UP, seed=seed)
                    outcomes[setting].append(CaseOutcome(case, result, 0.0))
        rows.append((text, {s: rates(o, frames, s) for s, o in outcomes.items()}))
        print(format_row(rows[-1]), flush=True)

    lines = [
        "# Speed against accuracy (engine settings on the evaluation's cases)",
        "",
        f"{platform.machine()}, {torch.get_num_threads()} torch threads, weights "
        f"{extractor.fingerprint[:12]} ({extractor.headings} headings), seeds "
        f"{' '.join(map(str, args.seeds))}, {args.views} views per shape, up prior; "
        f"load average {load_average():.2f} at the end. Rates in %, RRE<10/20/30 deg and "
        "RTE<5/10 cm; ms is the median engine time per query.",
        "",
        "| engine options | same | same MatchAcc | same top-1 | cross | cross MatchAcc "
        "| same ms | cross ms |",
        "|---|---|---|---|---|---|---|---|",
        *(format_row(row) for row in rows),
    ]
    publish("\n".join(lines) + "\n", args.out)


def rates(outcomes: list[CaseOutcome], frames: dict, setting: str) -> dict[str, Any]:
    """The evaluation's row for these outcomes, with the median engine time."""
    row = summarise(outcomes, frames, setting)["row"]
    row["ms"] = float(np.median([engine_ms(o) for o in outcomes]))
    return row


def format_row(row: tuple[str, dict[str, dict[str, Any]]]) -> str:
    text, by_setting = row
    cells = [text]
    for setting in ("same", "cross"):
        r = by_setting[setting]
        cells.append("/".join(f"{r[c]:.1f}" for c in RATE_COLUMNS))
        cells.append(f"{r['MatchAcc']:.1f}")
        if setting == "same":
            cells.append(f"{r['top-1']:.1f}")
    cells += [f"{by_setting[s]['ms']:.0f}" for s in ("same", "cross")]
    return "| " + " | ".join(cells) + " |"


if __name__ == "__main__":
    main()
