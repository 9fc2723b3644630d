"""Chairs and tables in one library: the answers with the category sent and without it.

One library holds the shared chairs and tables of a setting (*same*: the validation shapes
themselves; *cross*: the training shapes, so every answer is another instance); views of the
validation chairs and tables (``up`` given) are registered twice, naming their category and
naming none. Per setting, mode and observed category it reports the views right (within 10
degrees, to the nearest pose the observed shape's symmetry makes equal, and 5 cm), the views
answered from the observed shape itself (*same*), the views answered from the right category,
the answers' mean ``category_confidence`` and the median seconds per query; and how well the
``category_confidence`` of the answers without a category sent tells a right category from a
wrong one (AUROC). It also times the *cross* chair views against a library of
the training chairs alone, the baseline the mixed library is compared with. Prints a markdown
table and writes it to ``bench/results/categories.md``.

    .venv/bin/python bench/categories.py [--views 1] [--seed 0] [--model-dir model_store]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from _report import load_average, publish
from tqdm import tqdm

from catalign.data.shapes import SharedChairs, SharedTables
from catalign.data.views import WORLD_UP
from catalign.evaluation.metrics import auroc
from catalign.evaluation.protocol import TestCase, build_cases, frames_of, symmetries_of
from catalign.features.extractor import LearnedExtractor
from catalign.registration.engine import Engine
from catalign.registration.indexed import IndexedRegistrar
from catalign.registration.results import LibraryShape
from catalign.threads import limit_threads
from catalign.training.calibration import right_pose

RESULTS = Path(__file__).parent / "results" / "categories.md"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model-dir", type=Path, default=None)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)

    extractor = LearnedExtractor(args.model_dir) if args.model_dir else LearnedExtractor()
    sources = {"chair": SharedChairs(None), "table": SharedTables(None)}
    shapes = {
        (category, split): {i: source.metric(i) for i in source.ids(split)}
        for category, source in sources.items()
        for split in ("train", "val")
    }
    every = {i: s for group in shapes.values() for i, s in group.items()}
    category_of = {i: c for (c, _), group in shapes.items() for i in group}
    frames, symmetries = frames_of(every), symmetries_of(every)
    cases = {
        category: build_cases(shapes[category, "val"], args.views, args.seed, "upright")
        for category in sources
    }

    def engine_for(split: str, categories: tuple[str, ...]) -> Engine:
        registrar = IndexedRegistrar(extractor, name="learned")
        library = [
            LibraryShape(i, s.points, s.mesh, category)
            for category in categories
            for i, s in shapes[category, split].items()
        ]
        registrar.prepare(library)
        assert registrar.engine is not None
        return registrar.engine

    def run(engine: Engine, items: list[TestCase], sent: str | None, label: str) -> dict:
        right, own, category_right, seconds, shares = [], [], [], [], []
        for case in tqdm(items, desc=label):
            started = time.perf_counter()
            result = engine.register(case.points, up=WORLD_UP, seed=args.seed, category=sent)
            seconds.append(time.perf_counter() - started)
            right.append(right_pose(result.pose, result.model_id, case, frames, symmetries))
            own.append(result.model_id == case.shape_id)
            category_right.append(result.category == category_of[case.shape_id])
            shares.append(result.category_confidence)
        return {
            "cases": len(items),
            "right": 100 * np.mean(right),
            "own": 100 * np.mean(own),
            "category": 100 * np.mean(category_right),
            "seconds": float(np.median(seconds)),
            "share": float(np.mean([s for s in shares if s is not None] or [np.nan])),
            "shares": shares,
            "category_right": category_right,
        }

    rows = []
    for split, setting in (("val", "same"), ("train", "cross")):
        mixed = engine_for(split, ("chair", "table"))
        for observed in sources:
            for sent in (observed, None):
                mode = "category sent" if sent else "no category"
                label = f"{setting} {observed} {mode}"
                rows.append((setting, observed, mode, run(mixed, cases[observed], sent, label)))
    alone = engine_for("train", ("chair",))
    baseline = run(alone, cases["chair"], None, "cross chair, chairs alone")

    sizes = {key: len(group) for key, group in shapes.items()}
    lines = [
        "# Chairs and tables in one library",
        "",
        f"Library *same*: {sizes['chair', 'val']} validation chairs and {sizes['table', 'val']} "
        f"validation tables; *cross*: {sizes['chair', 'train']} training chairs and "
        f"{sizes['table', 'train']} training tables. {args.views} view(s) per validation shape, "
        f"seed {args.seed}, `up` given, weights `{args.model_dir or 'model_store'}`; load average "
        f"{load_average():.2f}. Right: within 10 degrees (to the nearest symmetric pose) and "
        "5 cm; own model: the observed shape's own CAD chosen (*same*); category: the answer's "
        "model is of the observed category.",
        "",
        "| setting | observed | mode | cases | right % | own model % | category % | "
        "category confidence | s/query |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for setting, observed, mode, row in rows:
        own = f"{row['own']:.1f}" if setting == "same" else "n/a"
        lines.append(
            f"| {setting} | {observed} | {mode} | {row['cases']} | {row['right']:.1f} | {own} | "
            f"{row['category']:.1f} | {row['share']:.3f} | {row['seconds']:.3f} |"
        )
    lines.append(
        f"| cross | chair | chairs alone | {baseline['cases']} | {baseline['right']:.1f} | n/a | "
        f"{baseline['category']:.1f} | {baseline['share']:.3f} | {baseline['seconds']:.3f} |"
    )
    unsent = [row for _, _, mode, row in rows if mode == "no category"]
    shares = np.array([s for row in unsent for s in row["shares"]], dtype=float)
    hits = np.array([h for row in unsent for h in row["category_right"]])
    known = np.isfinite(shares)
    separation = auroc(shares[known], hits[known])
    wrong = shares[known & ~hits]
    cross_chair = {
        mode: row
        for setting, observed, mode, row in rows
        if (setting, observed) == ("cross", "chair")
    }
    sent_ratio = cross_chair["category sent"]["seconds"] / baseline["seconds"]
    none_ratio = cross_chair["no category"]["seconds"] / baseline["seconds"]
    lines += [
        "",
        "Median seconds per query of the *cross* chair views, over the library of the training "
        f"chairs alone: category sent {sent_ratio:.2f}x, no category {none_ratio:.2f}x.",
        "",
        f"Without a category sent, {int((~hits).sum())} of {len(hits)} answers are of another "
        "category; their `category_confidence` "
        + (f"is {np.median(wrong):.3f} median" if len(wrong) else "does not arise")
        + f", that of the others {np.median(shares[known & hits]):.3f}; AUROC "
        + ("n/a" if separation is None else f"{separation:.3f}")
        + ".",
    ]
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
