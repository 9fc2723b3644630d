"""Retrieval at scale: the shared chairs and tables amid thousands of procedural distractors.

Each library holds every shared chair and table (the validation ones are observed, the training
ones are distractors of their category) and ``N`` procedural chairs (seeds from
:data:`FIRST_SEED`, far from those the retrieval encoders were trained on), built through
``catalign.library.index.build`` with every core, once per weights and ``N``, into ``--cache``
(for new retrieval encoders over the same features, described again from the cached one:
``catalign.library.redescribe``).
Every entry is a real build, except with ``--copies TOTAL``: then the largest library is also
grown to ``TOTAL`` entries by copies of its procedural distractors under new ids (``<id>-copy<k>``,
their arrays unchanged), as many entries as cannot be built on two cores in an hour. A copy
adds no shape the library did not hold, so those rows measure serving at that size (memory,
latency, the shortlist's scan), not how retrieval copes with that many different shapes. The
queries are views of the validation chairs and
tables with ``up`` given and their category sent, registered by the engine in this process.
Per library and observed category it reports the views answered with the observed shape's own
model (top-1), those whose own model was shortlisted, the views right (within 10 degrees, to
the nearest symmetric pose, and 5 cm), and the median and 95th-percentile seconds per query.
Prints a markdown table and writes it to ``bench/results/retrieval.md``.

    .venv/bin/python bench/retrieval.py [--distractors 0 1000 10000] [--pooled 0 1000]
        [--copies 100000] [--unfitted] [--engine NAME=VALUE...] [--views 2]
        [--seed 0] [--model-dir DIR]
        [--cache /tmp/catalign-retrieval] [--out bench/results/retrieval.md]

``--pooled`` also runs the baseline, the same weights shortlisting by pooled features, at
those distractor counts; ``--unfitted`` the shortlist by descriptors alone, without the
re-ranking by outlines (``engine.shortlist.fit_candidates`` None), on every library.
``--engine`` sets engine options for every run, as ``catalign evaluate --engine`` does.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import itertools
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import trimesh
from _report import load_average, publish
from tqdm import tqdm

from catalign.data.procedural import generate_chair
from catalign.data.shapes import Shape, SharedChairs, SharedTables
from catalign.data.views import WORLD_UP
from catalign.errors import DegenerateInputError, LibraryError
from catalign.evaluation.protocol import build_cases, frames_of, symmetries_of
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor, features_fingerprint
from catalign.features.retrieval import RETRIEVAL_DIR
from catalign.geometry.ncc import NCCFrame
from catalign.library.index import build
from catalign.library.loaded import load
from catalign.library.redescribe import redescribe
from catalign.library.store import (
    commit_changes,
    has_manifest,
    read_entry,
    read_manifest,
    write_entry,
)
from catalign.registration.config import EngineConfig, parse_options
from catalign.registration.engine import Engine
from catalign.threads import limit_threads
from catalign.training.calibration import right_pose

RESULTS = Path(__file__).parent / "results" / "retrieval.md"
FIRST_SEED = 100_000


def write_sources(folder: Path, shared: dict[str, dict[str, Shape]], distractors: int) -> None:
    """Every shape as a file in its category's sub-folder, as ``library build`` reads them."""
    for category, shapes in shared.items():
        place = folder / category
        place.mkdir(parents=True, exist_ok=True)
        for shape_id, shape in shapes.items():
            if shape.mesh is None:
                np.save(place / f"{shape_id}.npy", shape.points.astype(np.float32))
            else:
                mesh = trimesh.Trimesh(shape.mesh.vertices, shape.mesh.faces, process=False)
                mesh.export(place / f"{shape_id}.ply")
    for seed in tqdm(range(FIRST_SEED, FIRST_SEED + distractors), desc="distractors"):
        generate_chair(seed).export(folder / "chair" / f"proc-{seed}.ply")


def library_for(cache: Path, extractor: LearnedExtractor, shared: dict, distractors: int) -> Path:
    """The library of the shared shapes and ``distractors`` procedural chairs (built once, or
    described again from a cached one of the same features and other retrieval encoders)."""
    out = cache / extractor.fingerprint.replace("+", "_") / f"distractors-{distractors}"
    if not has_manifest(out):
        features = features_fingerprint(extractor.fingerprint)
        same_features = [
            folder
            for folder in sorted(cache.glob(f"{features}*/distractors-{distractors}"))
            if _features_of(folder) == features
        ]
        if same_features:
            partial = out.with_name(out.name + ".partial")
            shutil.rmtree(partial, ignore_errors=True)
            shutil.copytree(same_features[0], partial, ignore=shutil.ignore_patterns(".lock"))
            started = time.perf_counter()
            with tqdm(desc=f"describing {out.name} again", unit="entry") as bar:
                redescribe(partial, extractor, lambda done, total: bar.update(done - bar.n))
            partial.rename(out)
            print(f"described {out} again in {time.perf_counter() - started:.0f} s")
            return out
        with tempfile.TemporaryDirectory(dir=cache) as folder:
            write_sources(Path(folder), shared, distractors)
            started = time.perf_counter()
            build([folder], out, extractor, overwrite=True, workers=2)
            print(f"built {out} in {time.perf_counter() - started:.0f} s")
    return out


def _features_of(library_dir: Path) -> str | None:
    """Whose features a cached library holds; None where it holds no library this catalign
    reads (an older format: rebuilt rather than converted)."""
    try:
        return features_fingerprint(read_manifest(library_dir).fingerprint)
    except LibraryError:
        return None


def with_copies(library_dir: Path, total: int, workers: int) -> Path:
    """``library_dir`` grown to ``total`` entries by copies of its procedural distractors under
    new ids, in a folder beside it (made once, renamed into place when whole)."""
    out = library_dir.with_name(f"{library_dir.name}-copies-{total}")
    if has_manifest(out):
        return out
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(library_dir, partial, ignore=shutil.ignore_patterns(".lock", ".writing"))
    ids = read_manifest(partial).ids
    sources = [i for i in ids if i.startswith("proc-")]
    copies = [
        (sources[n % len(sources)], f"{sources[n % len(sources)]}-copy{n // len(sources)}")
        for n in range(total - len(ids))
    ]
    started = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        made = pool.map(functools.partial(_copy_entry, partial), copies, chunksize=64)
        records = dict(tqdm(made, total=len(copies), desc=f"copies for {out.name}"))
    commit_changes(partial, put=records)
    partial.rename(out)
    print(f"copied {len(copies)} entries into {out} in {time.perf_counter() - started:.0f} s")
    return out


def _copy_entry(library_dir: Path, names: tuple[str, str]) -> tuple[str, object]:
    """One entry written again under another id; its record."""
    source, target = names
    record = _records(library_dir)[source]
    entry = read_entry(library_dir, source, record)
    return target, write_entry(library_dir, dataclasses.replace(entry, model_id=target))


@functools.cache
def _records(library_dir: Path) -> dict:
    return read_manifest(library_dir).entries


def pooled_extractor(model_dir: Path | None, cache: Path) -> LearnedExtractor:
    """The same weights without their retrieval encoders (a folder of links to every file but
    ``retrieval/``): the shortlist then pools the features, as before the encoders."""
    source = model_dir or DEFAULT_MODEL_DIR
    folder = cache / "pooled-weights"
    folder.mkdir(exist_ok=True)
    for item in source.iterdir():
        link = folder / item.name
        if item.name not in (RETRIEVAL_DIR, "library") and not link.exists():
            link.symlink_to(item.resolve())
    return LearnedExtractor(folder)


def shared_cases(views: int, seed: int) -> tuple[dict, dict, dict, dict]:
    """The shared chairs and tables by category, the cases (``views`` of each validation
    shape) by category, and every shape's frame and symmetry."""
    sources = {"chair": SharedChairs(None), "table": SharedTables(None)}
    shared = {c: {i: s.metric(i) for i in s.ids()} for c, s in sources.items()}
    observed = {c: {i: shared[c][i] for i in s.ids("val")} for c, s in sources.items()}
    every = {i: s for group in shared.values() for i, s in group.items()}
    cases = {c: build_cases(observed[c], views, seed) for c in sources}
    return shared, cases, frames_of(every), symmetries_of(every)


def measure(
    kind: str,
    folder: Path,
    extractor: LearnedExtractor,
    cases: dict,
    frames: dict,
    symmetries: dict,
    seed: int,
    config: EngineConfig | None = None,
) -> list[tuple]:
    """Every case registered against the library in ``folder`` (by an engine of ``config``);
    a row per category."""
    library = load(folder, None)
    engine = Engine(extractor, library, config=config)
    rows = []
    for category, items in cases.items():
        own, listed, right, seconds, refused = [], [], [], [], 0
        for case in tqdm(items, desc=f"{len(library)} models, {category}"):
            started = time.perf_counter()
            try:
                result = engine.register(case.points, up=WORLD_UP, seed=seed, category=category)
            except DegenerateInputError:  # a view the service refuses (a table top edge-on)
                refused += 1
                for counted in (own, listed, right):
                    counted.append(False)
                continue
            seconds.append(time.perf_counter() - started)
            if result.model_id not in frames:  # a distractor: its frame from its entry
                frames[result.model_id] = NCCFrame.fit(library[result.model_id].points)
            own.append(result.model_id == case.shape_id)
            listed.append(case.shape_id in {c.model_id for c in result.candidates})
            right.append(right_pose(result.pose, result.model_id, case, frames, symmetries))
        in_category = int(np.sum(library.categories == category))
        rows.append(
            (kind, len(library), in_category, category, own, listed, right, seconds, refused)
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--distractors", type=int, nargs="+", default=[0, 1000, 10000])
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model-dir", type=Path, default=None)
    parser.add_argument(
        "--pooled", type=int, nargs="*", default=None, help="distractor counts of the baseline"
    )
    parser.add_argument(
        "--copies", type=int, default=None, help="also grow each library to this many entries"
    )
    parser.add_argument(
        "--unfitted", action="store_true", help="also shortlist without the outline fit"
    )
    parser.add_argument(
        "--engine", nargs="+", default=[], metavar="NAME=VALUE", help="engine options"
    )
    parser.add_argument("--cache", type=Path, default=Path("/tmp/catalign-retrieval"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    limit_threads(args.threads, total=args.threads)
    args.cache.mkdir(parents=True, exist_ok=True)

    extractor = LearnedExtractor(args.model_dir)
    shared, cases, frames, symmetries = shared_cases(args.views, args.seed)

    config = parse_options(args.engine)
    kinds = [("retrieval encoders", extractor)]
    if args.pooled is not None:
        kinds.append(("pooled features", pooled_extractor(args.model_dir, args.cache)))
    rows = []
    for distractors, (kind, described_by) in itertools.product(args.distractors, kinds):
        if kind == "pooled features" and distractors not in args.pooled:
            continue
        built = library_for(args.cache, described_by, shared, distractors)
        folders = [(kind, built)]
        largest = distractors == max(args.distractors)
        if args.copies is not None and kind == "retrieval encoders" and largest:
            grown = with_copies(built, args.copies, args.threads)
            folders.append((f"{kind}, copies", grown))
        for label, folder in folders:
            rows += measure(
                label, folder, described_by, cases, frames, symmetries, args.seed, config
            )
            if args.unfitted and kind == "retrieval encoders":
                unfitted = config.replaced(shortlist={"fit_candidates": None})
                rows += measure(
                    f"{label}, no outline fit", folder, described_by, cases, frames,
                    symmetries, args.seed, unfitted,
                )  # fmt: skip
    lines = [
        "# Retrieval at scale",
        "",
        f"Every shared chair and table plus N procedural chairs; {args.views} view(s) of each "
        f"validation shape, seed {args.seed}, `up` given, category sent; weights "
        f"`{args.model_dir or 'model_store'}`; engine options "
        f"{' '.join(args.engine) or 'the defaults'}; shortlisted by its retrieval encoders, the "
        "best 300 re-ranked by their outline fit (the baselines in the same run: without the "
        "fit, and by the mean and max of the features); "
        f"{args.threads} threads, load average {load_average():.2f}. Top-1: the observed shape's "
        "own model answered; shortlisted: its own model among the candidates registered; right: "
        "within 10 degrees (nearest symmetric pose) and 5 cm; refused: views the engine "
        "refuses as degenerate (counted wrong).",
        "",
        "| shortlist | models | of the category | observed | views | refused | top-1 % | "
        "shortlisted % | right % | median s | p95 s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for kind, size, in_category, category, own, listed, right, seconds, refused in rows:
        lines.append(
            f"| {kind} | {size} | {in_category} | {category} | {len(own)} | {refused} | "
            f"{100 * np.mean(own):.1f} | "
            f"{100 * np.mean(listed):.1f} | {100 * np.mean(right):.1f} | "
            f"{np.median(seconds):.3f} | {np.percentile(seconds, 95):.3f} |"
        )
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
