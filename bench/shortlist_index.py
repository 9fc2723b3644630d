"""The shortlist's index against the exact scan it replaces, on the retrieval bench's libraries.

For each library (the shared chairs and tables amid N procedural chairs, built or described
again by ``bench/retrieval.py`` into ``--cache``; with ``--copies`` also the one grown to that
many entries), the index is written (``catalign.library.shortlist_index.write_index``, timed,
its size on disk), the library loaded with it, and every view registered twice in the same
process: the exact scan (``shortlist.index_from=None``) and the index. It reports, per library
and observed category, how often the index's first shortlist is the exact one (same ids, same
order), the views answered with their own model and right (10 degrees, 5 cm) either way, and
the median seconds of the shortlist stage and of the whole query. ``--graphs`` also compares
the graph libraries (usearch, faiss, hnswlib, those installed) on the largest built library's
descriptors (copies repeat descriptors): build seconds, size, recall of the exact 256
nearest, microseconds a query.

    .venv/bin/python bench/shortlist_index.py [--distractors 1000 10000] [--copies 100000]
        [--graphs] [--candidates 256] [--views 2] [--seed 0] [--cache /tmp/catalign-retrieval]
        [--out bench/results/shortlist_index.md]
"""

from __future__ import annotations

import argparse
import importlib.util
import tempfile
import time
from pathlib import Path

import numpy as np
from _report import load_average, publish
from retrieval import library_for, shared_cases, with_copies
from tqdm import tqdm

import catalign.registration.stages.searcher as searcher
from catalign.data.views import WORLD_UP
from catalign.features.extractor import LearnedExtractor
from catalign.geometry.ncc import NCCFrame
from catalign.library.loaded import load
from catalign.library.shortlist_index import INDEX_DIR, unit_rows, write_index
from catalign.library.store import read_manifest
from catalign.registration.config import EngineConfig
from catalign.registration.engine import Engine
from catalign.threads import limit_threads
from catalign.training.calibration import right_pose

RESULTS = Path(__file__).parent / "results" / "shortlist_index.md"
NEIGHBOURS = 256


class FirstShortlists:
    """Records the shortlists the engine's searcher makes (its stage function, wrapped)."""

    def __init__(self) -> None:
        self.original = searcher.shortlist
        self.calls: list[list[str]] = []
        searcher.shortlist = self

    def __call__(self, *args, **kwargs) -> list[str]:
        found = self.original(*args, **kwargs)
        self.calls.append(found)
        return found


MODES = ("exact", "index")


def measure(
    folder: Path, extractor, cases: dict, frames, symmetries, seed: int, candidates: int
) -> list[tuple]:
    """Every case registered by the exact scan and by the index (``candidates`` neighbours a
    heading); a row per category."""
    written = write_index(folder, read_manifest(folder).entries)
    size_mb = sum(p.stat().st_size for p in (folder / INDEX_DIR).iterdir()) / 1e6
    library = load(folder, None)
    exact_only = EngineConfig().replaced(shortlist={"index_from": None})
    through = EngineConfig().replaced(shortlist={"index_candidates": candidates})
    engines = {
        "exact": Engine(extractor, library, config=exact_only),
        "index": Engine(extractor, library, config=through),
    }
    recorder = FirstShortlists()
    rows = []
    for category, items in cases.items():
        same = []
        seen = {m: {"own": [], "right": [], "stage": [], "total": []} for m in MODES}
        for case in tqdm(items, desc=f"{len(library)} models, {category}"):
            firsts = {}
            for mode, engine in engines.items():
                recorder.calls.clear()
                started = time.perf_counter()
                result = engine.register(case.points, up=WORLD_UP, seed=seed, category=category)
                seen[mode]["total"].append(time.perf_counter() - started)
                seen[mode]["stage"].append(result.timings_ms.get("shortlist", np.nan))
                firsts[mode] = recorder.calls[0] if recorder.calls else []
                if result.model_id not in frames:
                    frames[result.model_id] = NCCFrame.fit(library[result.model_id].points)
                seen[mode]["own"].append(result.model_id == case.shape_id)
                seen[mode]["right"].append(
                    right_pose(result.pose, result.model_id, case, frames, symmetries)
                )
            same.append(firsts["exact"] == firsts["index"])
        in_category = int(np.sum(library.categories == category))
        rows.append((len(library), in_category, category, written, size_mb, same, seen))
    return rows


def compare_graphs(folder: Path, queries: int, seed: int) -> list[str]:
    """The graph libraries installed, on ``folder``'s descriptors: each library's own entries,
    nudged, as the queries."""
    records = read_manifest(folder).entries
    vectors = unit_rows([records[i].descriptor for i in sorted(records)])
    rng = np.random.default_rng(seed)
    picked = vectors[rng.choice(len(vectors), queries, replace=False)]
    probes = unit_rows(
        [
            (v + 0.3 * rng.normal(size=v.shape) / np.sqrt(v.size)).astype("<f4").tobytes()
            for v in picked
        ]
    )
    exact = np.argsort(-(probes @ vectors.T), axis=1)[:, :NEIGHBOURS]
    lines = [
        "",
        f"Graph libraries on the {len(vectors)} descriptors of `{folder.name}`, {queries} "
        f"nudged entries as queries, the {NEIGHBOURS} nearest asked for, one query at a time "
        "on one thread; built on every core.",
        "",
        "| graph | build s | MB on disk | open s | recall of the exact nearest | µs a query |",
        "|---|---|---|---|---|---|",
    ]
    for name, graph in _graphs(vectors.shape[1]):
        if graph is None:
            lines.append(f"| {name} | not installed | | | | |")
            continue
        with tempfile.TemporaryDirectory() as scratch:
            started = time.perf_counter()
            graph.build(vectors)
            built = time.perf_counter() - started
            path = Path(scratch) / "graph"
            graph.save(path)
            size = path.stat().st_size / 1e6
            started = time.perf_counter()
            graph.open(path)
            opened = time.perf_counter() - started
            found, seconds = [], []
            for probe in probes:
                started = time.perf_counter()
                found.append(graph.search(probe, NEIGHBOURS))
                seconds.append(time.perf_counter() - started)
        recall = np.mean(
            [len(set(f) & set(e)) / NEIGHBOURS for f, e in zip(found, exact, strict=True)]
        )
        lines.append(
            f"| {name} | {built:.1f} | {size:.0f} | {opened:.3f} | {recall:.3f} | "
            f"{1e6 * np.median(seconds):.0f} |"
        )
    return lines


class _Usearch:
    def __init__(self, ndim: int) -> None:
        from usearch.index import Index

        self.Index, self.ndim = Index, ndim

    def build(self, vectors: np.ndarray) -> None:
        from catalign.library.shortlist_index import CONNECTIVITY, EXPANSION_ADD

        self.graph = self.Index(
            ndim=self.ndim,
            metric="ip",
            dtype="f32",
            connectivity=CONNECTIVITY,
            expansion_add=EXPANSION_ADD,
        )
        self.graph.add(np.arange(len(vectors), dtype=np.uint64), vectors)

    def save(self, path: Path) -> None:
        self.graph.save(str(path))

    def open(self, path: Path) -> None:
        self.graph = self.Index.restore(str(path), view=True)
        self.graph.expansion_search = 2 * NEIGHBOURS

    def search(self, probe: np.ndarray, count: int) -> np.ndarray:
        return self.graph.search(probe, count, threads=1).keys


class _Faiss:
    def __init__(self, ndim: int) -> None:
        import faiss

        self.faiss, self.ndim = faiss, ndim

    def build(self, vectors: np.ndarray) -> None:
        self.graph = self.faiss.IndexHNSWFlat(self.ndim, 16, self.faiss.METRIC_INNER_PRODUCT)
        self.graph.hnsw.efConstruction = 128
        self.graph.add(vectors)

    def save(self, path: Path) -> None:
        self.faiss.write_index(self.graph, str(path))

    def open(self, path: Path) -> None:
        self.graph = self.faiss.read_index(str(path))
        self.graph.hnsw.efSearch = 2 * NEIGHBOURS
        self.faiss.omp_set_num_threads(1)

    def search(self, probe: np.ndarray, count: int) -> np.ndarray:
        return self.graph.search(probe[None], count)[1][0]


class _Hnswlib:
    def __init__(self, ndim: int) -> None:
        import hnswlib

        self.hnswlib, self.ndim = hnswlib, ndim

    def build(self, vectors: np.ndarray) -> None:
        self.graph = self.hnswlib.Index(space="ip", dim=self.ndim)
        self.graph.init_index(max_elements=len(vectors), M=16, ef_construction=128)
        self.graph.add_items(vectors, np.arange(len(vectors)))
        self.count = len(vectors)

    def save(self, path: Path) -> None:
        self.graph.save_index(str(path))

    def open(self, path: Path) -> None:
        self.graph = self.hnswlib.Index(space="ip", dim=self.ndim)
        self.graph.load_index(str(path), max_elements=self.count)
        self.graph.set_ef(2 * NEIGHBOURS)
        self.graph.set_num_threads(1)

    def search(self, probe: np.ndarray, count: int) -> np.ndarray:
        return self.graph.knn_query(probe[None], k=count)[0][0]


def _graphs(ndim: int):
    """Each graph library: its adapter, or None where it is not installed."""
    for name, module, adapter in (
        ("usearch (shipped)", "usearch", _Usearch),
        ("faiss-cpu", "faiss", _Faiss),
        ("hnswlib", "hnswlib", _Hnswlib),
    ):
        yield name, adapter(ndim) if importlib.util.find_spec(module) else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--distractors", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--copies", type=int, default=None)
    parser.add_argument("--graphs", action="store_true")
    default = EngineConfig().shortlist.index_candidates
    parser.add_argument("--candidates", type=int, default=default, help="neighbours a heading")
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/catalign-retrieval"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)
    extractor = LearnedExtractor(None)
    shared, cases, frames, symmetries = shared_cases(args.views, args.seed)
    folders = [library_for(args.cache, extractor, shared, n) for n in args.distractors]
    if args.copies is not None:
        folders.append(with_copies(folders[-1], args.copies, args.threads))
    rows = []
    for folder in folders:
        rows += measure(folder, extractor, cases, frames, symmetries, args.seed, args.candidates)
    lines = [
        "# The shortlist's index against the exact scan",
        "",
        f"The retrieval bench's libraries; {args.views} view(s) of each validation shape, seed "
        f"{args.seed}, `up` given, category sent; {args.threads} threads, load average "
        f"{load_average():.2f}; the index's {args.candidates} nearest entries a heading. Same "
        "shortlist: the index's first shortlist of a query is the exact scan's, ids and order. "
        "Top-1 and right (10 degrees, 5 cm) as in the retrieval bench, exact → index; times "
        "are medians, exact → index.",
        "",
        "| models | of the category | observed | views | index written s | index MB | "
        "same shortlist % | top-1 % | right % | shortlist ms | query s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for size, in_category, category, written, size_mb, same, seen in rows:
        exact, index = seen["exact"], seen["index"]
        lines.append(
            f"| {size} | {in_category} | {category} | {len(same)} | {written.seconds:.1f} | "
            f"{size_mb:.0f} | {100 * np.mean(same):.1f} | "
            f"{100 * np.mean(exact['own']):.1f} → {100 * np.mean(index['own']):.1f} | "
            f"{100 * np.mean(exact['right']):.1f} → {100 * np.mean(index['right']):.1f} | "
            f"{np.median(exact['stage']):.1f} → {np.median(index['stage']):.1f} | "
            f"{np.median(exact['total']):.3f} → {np.median(index['total']):.3f} |"
        )
    if args.graphs:
        lines += compare_graphs(folders[len(args.distractors) - 1], 200, args.seed)
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
