"""What one library change costs as the library grows: the SQLite catalogue (format 3) beside
the JSON manifest it replaced (format 2), on libraries of 10^3 to 10^5 entries, in the same run.

Each entry is a tiny synthetic entry file (256 bytes named by its sha256, as a real one is):
the catalogue's cost does not depend on what the files hold, and 10^5 real entries would take
80 GB. For each size:

* **add**: what ``catalign library add`` does once the shape is described (describing takes the
  same time at any size and is left out): under the writer lock, the new id's row looked up, the
  entry file written (temporary name, fsync, rename) and one transaction committed.
* **remove**: ``catalign.library.index.remove`` of one id, as the command runs it.
* **remove after a killed write**: the same, when an earlier writer's mark makes it sweep the
  entries folder for that writer's leftovers (every file listed against every row).
* **read all**: every record read and checked (``read_manifest``), as ``library info`` and a
  server's load do.
* **JSON**: format 2's way, reimplemented here as it was: read and parse the whole manifest,
  write the entry file, write the manifest of every record again (temporary name, fsync,
  rename), then sweep the entries folder; a remove the same without the entry file.

Medians of ``--runs`` adds and as many removes (each add's id removed again, so the size stays).

    .venv/bin/python bench/catalogue.py [--sizes 1000 10000 100000] [--runs 7]
        [--out bench/results/catalogue.md]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _report import load_average, publish

from catalign.atomic import atomic_write_bytes, fsync_directory
from catalign.library.index import remove
from catalign.library.legacy import read_legacy
from catalign.library.records import ENTRIES_DIR, EntryRecord, Manifest, entry_file_name
from catalign.library.store import (
    WRITING_NAME,
    begin_write,
    commit,
    commit_changes,
    read_manifest,
    utc_now,
    writer_lock,
)


def entry(model_id: str) -> tuple[bytes, EntryRecord]:
    """A tiny entry file's bytes and its record, with a real record's fields and sizes."""
    data = hashlib.sha256(model_id.encode()).digest() * 8
    sha256 = hashlib.sha256(data).hexdigest()
    record = EntryRecord(
        file=entry_file_name(model_id, sha256),
        sha256=sha256,
        source=f"/data/cad/chairs/{model_id}.ply",
        source_sha256=hashlib.sha256(data[::-1]).hexdigest(),
        units="m",
        num_points=10_000,
        num_keypoints=2_900,
        bbox_min=(-0.3227870541621556, -0.5621256571804353, -0.3330305759897203),
        bbox_max=(0.3227870541621556, 0.5621256571804353, 0.3330305759897203),
        size=(0.6455741083243112, 1.1242513143608706, 0.6660611519794406),
        symmetry=1,
    )
    return data, record


def library_of(folder: Path, size: int) -> Manifest:
    """Entry files for ``size`` ids in ``folder`` and the manifest that names them."""
    (folder / ENTRIES_DIR).mkdir(parents=True)
    records = {}
    for i in range(size):
        data, record = entry(f"m{i:07d}")
        (folder / record.file).write_bytes(data)
        records[f"m{i:07d}"] = record
    now = utc_now()
    return Manifest("0" * 64, 0.025, now, now, records)


def catalogue_add(folder: Path, model_id: str) -> None:
    data, record = entry(model_id)
    with writer_lock(folder):
        read_manifest(folder, ids=[model_id])  # is the id new? (index.add's check)
        begin_write(folder)
        atomic_write_bytes(folder / record.file, data, sync_directory=False)
        commit_changes(folder, put={model_id: record}, updated=utc_now())


def catalogue_remove_after_a_kill(folder: Path, model_id: str) -> None:
    (folder / WRITING_NAME).write_bytes(b"")  # the mark a killed writer leaves
    remove(folder, [model_id])


def json_write(folder: Path, manifest: Manifest) -> None:
    """Format 2's commit: the whole manifest rewritten atomically, then the folder swept."""
    raw = {
        "format_version": 2,
        "extractor": {"fingerprint": manifest.fingerprint, "voxel_size": manifest.voxel_size},
        "created": manifest.created,
        "updated": manifest.updated,
        "entries": {i: manifest.entries[i].to_json() for i in manifest.ids},
        "engine": manifest.engine,
        "category": manifest.category,
    }
    entries_dir = folder / ENTRIES_DIR
    fsync_directory(entries_dir)
    atomic_write_bytes(folder / "manifest.json", (json.dumps(raw, indent=2) + "\n").encode())
    referenced = {r.file for r in manifest.entries.values()}
    for name in os.listdir(entries_dir):
        if f"{ENTRIES_DIR}/{name}" not in referenced:
            (entries_dir / name).unlink()


def json_add(folder: Path, model_id: str) -> None:
    current = read_legacy(folder)
    data, record = entry(model_id)
    atomic_write_bytes(folder / record.file, data, sync_directory=False)
    entries = {**current.entries, model_id: record}
    json_write(folder, Manifest(current.fingerprint, current.voxel_size, current.created,
                                utc_now(), entries))  # fmt: skip


def json_remove(folder: Path, model_id: str) -> None:
    current = read_legacy(folder)
    entries = {i: r for i, r in current.entries.items() if i != model_id}
    json_write(folder, Manifest(current.fingerprint, current.voxel_size, current.created,
                                utc_now(), entries))  # fmt: skip


def median_ms(runs: int, work: Callable[[int], object]) -> float:
    times = []
    for run in range(runs):
        started = time.perf_counter()
        work(run)
        times.append(1000 * (time.perf_counter() - started))
    return float(np.median(times))


def measure(size: int, runs: int, work_dir: Path) -> dict[str, float]:
    new, old = work_dir / f"catalogue-{size}", work_dir / f"json-{size}"
    commit(new, library_of(new, size))
    json_write(old, library_of(old, size))
    added = [f"new{run:03d}" for run in range(runs)]
    row = {
        "add": median_ms(runs, lambda run: catalogue_add(new, added[run])),
        "remove": median_ms(runs, lambda run: remove(new, [added[run]])),
        "read": median_ms(runs, lambda run: read_manifest(new)),
    }
    for model_id in added:
        catalogue_add(new, model_id)
    row["swept"] = median_ms(runs, lambda run: catalogue_remove_after_a_kill(new, added[run]))
    row |= {
        "json add": median_ms(runs, lambda run: json_add(old, added[run])),
        "json remove": median_ms(runs, lambda run: json_remove(old, added[run])),
        "json read": median_ms(runs, lambda run: read_legacy(old)),
        "catalogue MB": (new / "catalogue.sqlite").stat().st_size / 1e6,
        "json MB": (old / "manifest.json").stat().st_size / 1e6,
    }
    assert len(read_manifest(new).entries) == len(read_legacy(old).entries) == size
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--work", type=Path, default=None, help="Scratch folder (default: /tmp)")
    parser.add_argument("--out", type=Path, default=Path("bench/results/catalogue.md"))
    args = parser.parse_args()

    rows = []
    with tempfile.TemporaryDirectory(prefix="catalign-catalogue-", dir=args.work) as work:
        for size in args.sizes:
            rows.append((size, measure(size, args.runs, Path(work))))
            print(f"{size:,} entries: {rows[-1][1]}", flush=True)

    lines = [
        "# One library change by library size: SQLite catalogue (format 3) and JSON manifest "
        "(format 2)",
        "",
        f"{platform.machine()}, load average {load_average():.2f}; median of {args.runs} runs "
        "each, tiny synthetic entry files (the cost does not depend on their contents); "
        "times in ms. An add leaves describing the shape out; a remove after a killed write "
        "sweeps the entries folder.",
        "",
        "| entries | add | JSON add | remove | JSON remove | remove after a killed write "
        "| read all | JSON read all | catalogue MB | JSON MB |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for size, r in rows:
        lines.append(
            f"| {size:,} | {r['add']:.1f} | {r['json add']:.0f} | {r['remove']:.1f} "
            f"| {r['json remove']:.0f} | {r['swept']:.0f} | {r['read']:.0f} "
            f"| {r['json read']:.0f} | {r['catalogue MB']:.1f} | {r['json MB']:.1f} |"
        )
    publish("\n".join(lines) + "\n", args.out)


if __name__ == "__main__":
    main()
