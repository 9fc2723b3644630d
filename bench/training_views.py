"""Engine settings compared on views of the training chairs: more views than validation offers.

The validation split gives 54 views per setting and seed, where a case is almost 2 points; a
setting chosen on them fits them a little. The calibration's views (``catalign calibrate``:
the 61 training chairs, ``--views`` each, seed 2000, ``up`` given) are many more, and no engine
option was chosen on them: *same* registers them against a library of all the training chairs,
*cross* in 4 folds, each fold's views against a library of the other three (46 chairs). The
features were trained on these chairs, so the rates are higher than on validation chairs; what
the table is for is the difference between settings on the same views. Each library index is
built once and every setting runs on it. Prints a markdown table and writes it to
``bench/results/training-views.md``.

    .venv/bin/python bench/training_views.py [--views 4] \
        [--configs default orient.heading_mass=none verify.coverage_cell=0.75]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _report import load_average, publish
from tqdm import tqdm

from catalign.data.shapes import SharedChairs
from catalign.data.views import WORLD_UP
from catalign.evaluation.protocol import build_cases, frames_of, metric_shapes
from catalign.features.extractor import LearnedExtractor
from catalign.registration.config import parse_options
from catalign.registration.engine import Engine
from catalign.registration.indexed import IndexedRegistrar
from catalign.registration.results import LibraryShape
from catalign.threads import limit_threads
from catalign.training.calibration import plans, right_pose

RESULTS = Path(__file__).parent / "results" / "training-views.md"
SEED = 2000  # the calibration's views


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--configs", nargs="+", default=["default"])
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)  # as the server's workers run
    configs = {
        text: parse_options([] if text == "default" else text.split(",")) for text in args.configs
    }

    extractor = LearnedExtractor()
    chairs = SharedChairs(None)
    ids = sorted(chairs.ids("train"))
    shapes = metric_shapes(chairs, ids)
    frames = frames_of(shapes)
    # right[setting][config] and top1[config]: one flag per view
    right: dict[str, dict[str, list[bool]]] = {"same": {}, "cross": {}}
    top1: dict[str, list[bool]] = {}
    for library_ids, observed_ids, setting in plans(ids):
        registrar = IndexedRegistrar(extractor, name="learned")
        registrar.prepare([LibraryShape(i, shapes[i].points, shapes[i].mesh) for i in library_ids])
        assert registrar.engine is not None
        cases = build_cases({i: shapes[i] for i in observed_ids}, args.views, SEED, "upright")
        for text, config in configs.items():
            engine = Engine(extractor, registrar.engine.library, config=config)
            for case in tqdm(cases, desc=f"{setting} {text}"):
                result = engine.register(case.points, up=WORLD_UP, seed=SEED)
                hit = right_pose(result.pose, result.model_id, case, frames)
                right[setting].setdefault(text, []).append(hit)
                if setting == "same":
                    top1.setdefault(text, []).append(result.model_id == case.shape_id)

    lines = [
        "# Engine settings on views of the training chairs",
        "",
        f"{len(ids)} training chairs, {args.views} views each, seed {SEED}, `up` given; "
        f"load average {load_average():.2f}. Right: within 10 degrees and 5 cm "
        "(category-level), as `confidence` means it.",
        "",
        "| engine options | *same* right | *same* top-1 | *cross* right |",
        "|---|---|---|---|",
    ]
    for text in configs:
        same, cross, first = right["same"][text], right["cross"][text], top1[text]
        lines.append(
            f"| {text} | {sum(same)}/{len(same)} ({100 * np.mean(same):.1f} %) | "
            f"{sum(first)}/{len(first)} ({100 * np.mean(first):.1f} %) | "
            f"{sum(cross)}/{len(cross)} ({100 * np.mean(cross):.1f} %) |"
        )
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
