"""What the shortlist costs as the library grows: the engine's shortlist stage on synthetic
libraries of 10^3 to 10^5 entries, beside the plain reference (each heading scored on its own
float64 copy of the descriptors, every entry sorted) in the same run.

The scores are the engine's (:func:`catalign.library.retrieval.retrieval_scores`: cosine of the
global descriptors, size and height penalties); the stage scores all headings in one product
over unit descriptors kept with the library, and sorts only the best ``k``. Both give the same
ids in the same order (tested in ``tests/library/test_retrieval.py``); this measures the time.

    .venv/bin/python bench/shortlist.py [--sizes 1000 10000 100000] [--headings 8] [--k 10]
        [--runs 7] [--out bench/results/shortlist.md]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
from _report import load_average, publish

from catalign.library.retrieval import height_penalty, size_penalty
from catalign.registration.stages.describe import QueryView
from catalign.registration.stages.shortlist import shortlist

WIDTH = 64  # the global descriptor of 32-dim features: mean and max


class SyntheticLibrary:
    """What the shortlist reads of a library: ids, descriptors, unit descriptors, sizes."""

    def __init__(self, size: int, rng: np.random.Generator) -> None:
        self.ids = [f"m{i:07d}" for i in range(size)]
        self.descriptors = rng.normal(size=(size, WIDTH)).astype(np.float32)
        norms = np.linalg.norm(self.descriptors, axis=1, keepdims=True)
        self.unit_descriptors = self.descriptors / norms
        self.sizes = rng.uniform(0.4, 1.1, (size, 3))

    def __len__(self) -> int:
        return len(self.ids)


def reference(library: SyntheticLibrary, views: list[np.ndarray], k: int) -> list[str]:
    """Each heading scored alone in float64 over the raw descriptors, then a full sort."""
    size, height = np.array([0.5, 0.8, 0.5]), 0.8
    per_view = []
    for query in views:
        models = library.descriptors.astype(np.float64)
        norms = np.linalg.norm(models, axis=1) * np.linalg.norm(query)
        scores = models @ query.astype(np.float64) / np.maximum(norms, 1e-12)
        scores -= size_penalty(size, library.sizes) + height_penalty(height, library.sizes[:, 1])
        per_view.append(scores)
    order = np.argsort(-np.max(per_view, axis=0), kind="stable")
    return [library.ids[i] for i in order[:k]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--headings", type=int, default=8)
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--out", type=Path, default=Path("bench/results/shortlist.md"))
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    # Key points spanning a chair-sized box: the stage reads the query's size from them.
    keypoints = rng.uniform(0, 1, (200, 3)) * np.array([0.5, 0.8, 0.5])
    rows = []
    for size in args.sizes:
        library = SyntheticLibrary(size, rng)
        features = [rng.normal(size=(200, WIDTH // 2)) for _ in range(args.headings)]
        views = [QueryView(keypoints, f) for f in features]
        descriptors = [np.concatenate([f.mean(0), f.max(0)]) for f in features]
        stage_ms, reference_ms = [], []
        for _ in range(args.runs):
            started = time.perf_counter()
            shortlist(library, views, args.k, None)  # type: ignore[arg-type]
            stage_ms.append(1000 * (time.perf_counter() - started))
            started = time.perf_counter()
            reference(library, descriptors, args.k)
            reference_ms.append(1000 * (time.perf_counter() - started))
        rows.append((size, float(np.median(stage_ms)), float(np.median(reference_ms))))

    lines = [
        f"# Shortlist cost by library size ({args.headings} headings, k={args.k})",
        "",
        f"{platform.machine()}, load average {load_average():.2f}; median of {args.runs} runs "
        "each, synthetic descriptors (the cost does not depend on their values).",
        "",
        "| entries | shortlist stage ms | reference ms | reference / stage |",
        "| ---: | ---: | ---: | ---: |",
    ]
    for size, stage, ref in rows:
        lines.append(f"| {size:,} | {stage:.1f} | {ref:.1f} | {ref / stage:.1f}x |")
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
