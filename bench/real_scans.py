"""The real ScanNet chairs through the engine, with ``up`` (+Z) and without it.

There is no CAD pose for them (``../shared/data/real_scans/README.md``), so the table reports
what can be judged: the model chosen, how far the answer tilts the chair from standing upright
(+Z), the fit (fitness and inlier ratio over the points kept), the answer's confidence (does
it warn when the chair comes back lying down?) and the points set aside.

A second table asks whether the answer moves with the sensor: each scan is also registered after
``--motions`` random rigid motions (20 to 60 degrees about a random axis, a shift of about a
metre; ``up``, when given, moved with it), under each engine setting of ``--configs``
(``name=value`` fields joined by commas, ``default`` for none changed), and counted are the
answers with the same model, and those whose pose is the moved pose of the unmoved answer
within 2 degrees and 2 cm; and, unmoved, the answers with another random seed that keep the
model (how near a tie the scan is).
Prints the tables and writes them to ``bench/results/real_scans.md``.

    .venv/bin/python bench/real_scans.py [--scans DIR] [--model-dir DIR] [--library DIR]
        [--motions 8] [--configs default heading_mass=none]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _report import load_average, publish

from catalign.data.shapes import default_chairs_root
from catalign.features.extractor import LearnedExtractor
from catalign.frames import MODEL_UP
from catalign.geometry.se3 import axis_angle, make_pose, rotation_error_deg, transform
from catalign.library.loaded import Library, load
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.config import EngineConfig, parse_options
from catalign.registration.engine import Engine
from catalign.threads import limit_threads

RESULTS = Path(__file__).parent / "results" / "real_scans.md"
WORLD_UP = np.array([0.0, 0.0, 1.0])


def tilt_deg(rotation: np.ndarray) -> float:
    """Degrees between the posed model's up and +Z."""
    return float(np.degrees(np.arccos(np.clip((rotation @ MODEL_UP) @ WORLD_UP, -1.0, 1.0))))


def motions(count: int, seed: int = 11) -> list[np.ndarray]:
    """``count`` random rigid motions a hand-held sensor could add."""
    rng = np.random.default_rng(seed)
    return [
        make_pose(
            axis_angle(rng.normal(size=3), np.radians(rng.uniform(20, 60))), rng.normal(size=3)
        )
        for _ in range(count)
    ]


def stability(
    engine: Engine, scans: dict[str, np.ndarray], moves: list[np.ndarray], with_up: bool
) -> str:
    """Answers after each motion with the unmoved answer's model, and those whose pose is
    also its moved pose within 2 degrees and 2 cm, and the answers with another random seed
    that keep the model, as a table row's cells."""
    same = agree = reseeded = 0
    up = WORLD_UP if with_up else None
    for points in scans.values():
        before = engine.register(points, up=up, seed=0)
        again = engine.register(points, up=up, seed=1)
        reseeded += again.model_id == before.model_id
        for move in moves:
            moved_up = None if up is None else move[:3, :3] @ up
            after = engine.register(transform(points, move), up=moved_up, seed=0)
            expected = move @ before.pose
            same += after.model_id == before.model_id
            agree += (
                after.model_id == before.model_id
                and rotation_error_deg(after.pose[:3, :3], expected[:3, :3]) <= 2.0
                and np.linalg.norm(after.pose[:3, 3] - expected[:3, 3]) <= 0.02
            )
    trials = len(scans) * len(moves)
    return (
        f"{trials} | {100 * same / trials:.0f} % | {100 * agree / trials:.0f} % | "
        f"{reseeded} of {len(scans)}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=Path, default=default_chairs_root().parent / "real_scans")
    parser.add_argument("--model-dir", type=Path, default=None)
    parser.add_argument("--library", type=Path, default=DEFAULT_MODEL_DIR / "library")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--motions", type=int, default=8, help="rigid motions of each scan (0: no such table)"
    )
    parser.add_argument("--configs", nargs="+", default=["default"])
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)  # as the server's workers run
    configs = {
        text: parse_options([] if text == "default" else text.split(",")) for text in args.configs
    }
    files = sorted(args.scans.glob("*.npy"))
    if not files:
        raise SystemExit(f"no scans in {args.scans}")

    extractor = LearnedExtractor(args.model_dir)
    engine = Engine(extractor, load(args.library, extractor.fingerprint))
    lines = [
        "# Real ScanNet chairs",
        "",
        f"{len(files)} scans, library {args.library.name} ({len(engine.library)} models), "
        f"weights {extractor.fingerprint[:12]}; load average {load_average():.2f}. Tilt: degrees "
        "between the posed model's up and +Z (0 = standing upright).",
        "",
        "| scan | points | `up` | model | tilt deg | fitness | inlier ratio | confidence "
        "| set aside | ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    scans = {path.stem: np.load(path).astype(np.float64) for path in files}
    upright = {"given": 0, "estimated": 0}
    lying_confidence = {"given": [], "estimated": []}  # of answers more than 10 degrees off
    for name, points in scans.items():
        for label, up in (("given", WORLD_UP), ("estimated", None)):
            result = engine.register(points, up=up, seed=0)
            tilt = tilt_deg(result.pose[:3, :3])
            upright[label] += tilt <= 10.0
            if tilt > 10.0:
                lying_confidence[label].append(result.confidence or 0.0)
            lines.append(
                f"| {name} | {len(points)} | {label} | {result.model_id} | {tilt:.1f} | "
                f"{result.fitness:.2f} | {result.inlier_ratio:.2f} | "
                f"{_or_dash(result.confidence)} | {result.points_set_aside} | "
                f"{sum(result.timings_ms.values()):.0f} |"
            )
    lines += [
        "",
        f"Upright within 10 degrees: {upright['given']} of {len(files)} with `up`, "
        f"{upright['estimated']} of {len(files)} without. Highest confidence of an answer "
        "more than 10 degrees from upright: "
        + ", ".join(
            f"{_or_dash(max(found, default=None))} {label}"
            for label, found in lying_confidence.items()
        )
        + ".",
    ]
    if args.motions > 0:
        lines += stability_table(extractor, engine.library, configs, scans, args.motions)
    publish("\n".join(lines) + "\n", args.out)


def stability_table(
    extractor: LearnedExtractor,
    library: Library,
    configs: dict[str, EngineConfig],
    scans: dict[str, np.ndarray],
    count: int,
) -> list[str]:
    """The lines of the table of answers under ``count`` rigid motions and another seed, one
    row per engine configuration and way of giving ``up``."""
    lines = [
        "",
        f"Under {count} random rigid motions of each scan (`up`, when given, moved "
        "along), and with another random seed (1 instead of 0):",
        "",
        "| engine options | `up` | moved answers | same model | same model and pose "
        "(2 deg, 2 cm) | same model, seed 1 |",
        "|---|---|---|---|---|---|",
    ]
    moves = motions(count)
    for text, config in configs.items():
        moved = Engine(extractor, library, config=config)
        for label, with_up in (("given", True), ("none", False)):
            lines.append(f"| {text} | {label} | {stability(moved, scans, moves, with_up)} |")
    return lines


def _or_dash(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


if __name__ == "__main__":
    main()
