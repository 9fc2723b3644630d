"""The real ScanNet chairs through the engine, with ``up`` (+Z) and without it.

There is no CAD pose for them (``../shared/data/real_scans/README.md``), so the table reports
what can be judged: the model chosen, how far the answer tilts the chair from standing upright
(+Z), the fit (fitness and inlier ratio over the points kept) and the points set aside. Prints
a markdown table and writes it to ``bench/results/real_scans.md``.

    .venv/bin/python bench/real_scans.py [--scans DIR] [--model-dir DIR] [--library DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from _report import load_average, publish

from catalign.data.shapes import default_chairs_root
from catalign.features.extractor import LearnedExtractor
from catalign.frames import MODEL_UP
from catalign.library.index import load
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.engine import Engine

RESULTS = Path(__file__).parent / "results" / "real_scans.md"
WORLD_UP = np.array([0.0, 0.0, 1.0])


def tilt_deg(rotation: np.ndarray) -> float:
    """Degrees between the posed model's up and +Z."""
    return float(np.degrees(np.arccos(np.clip((rotation @ MODEL_UP) @ WORLD_UP, -1.0, 1.0))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=Path, default=default_chairs_root().parent / "real_scans")
    parser.add_argument("--model-dir", type=Path, default=None)
    parser.add_argument("--library", type=Path, default=DEFAULT_MODEL_DIR / "library")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
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
        "| scan | points | `up` | model | tilt deg | fitness | inlier ratio | set aside | ms |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    upright = {"given": 0, "estimated": 0}
    for path in files:
        points = np.load(path).astype(np.float64)
        for label, up in (("given", WORLD_UP), ("estimated", None)):
            result = engine.register(points, up=up, seed=0)
            tilt = tilt_deg(result.pose[:3, :3])
            upright[label] += tilt <= 10.0
            lines.append(
                f"| {path.stem} | {len(points)} | {label} | {result.model_id} | {tilt:.1f} | "
                f"{result.fitness:.2f} | {result.inlier_ratio:.2f} | {result.points_set_aside} | "
                f"{sum(result.timings_ms.values()):.0f} |"
            )
    lines += [
        "",
        f"Upright within 10 degrees: {upright['given']} of {len(files)} with `up`, "
        f"{upright['estimated']} of {len(files)} without.",
    ]
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
