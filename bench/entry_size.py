"""What a library's entries take on disk and what reading one back costs, per library as its
files are, so that a library built in the current entry layout and one built in the layout
before it (which ``catalign.library.entry_codec`` still reads) can be set side by side.

The layouts, told apart by their members:

* **current**: the surface as 12-bit steps stored column by column in sorted order
  (``surface_steps``), the key points as 16-bit steps across the distance grid's box, the
  grid's levels in six bits; the surface and the grid LZMA-compressed, the rest deflated;
* **before**: the surface as 16-bit rows in sampling order (``point_steps``), float32 key
  points, the grid's 255 levels, every member deflated.

Per library: the median and mean entry file, the share of files of at most 100 KB, each large
member's median compressed size, and the median time to read an entry back (``npz_arrays``
then ``entry_from_arrays``, as a server does when a query shortlists it) and to encode its
arrays again with each member's own method (what writing it costs, narrowing aside).

    .venv/bin/python bench/entry_size.py LIBRARY... [--limit 200]
        [--out bench/results/entry_size.md]
"""

from __future__ import annotations

import argparse
import io
import platform
import statistics
import time
import zipfile
from pathlib import Path

import numpy as np
from _report import load_average, publish

from catalign.library.entry_codec import entry_from_arrays
from catalign.library.npz import npz_arrays
from catalign.library.store import read_manifest

MEMBERS = {  # the table's columns: the member in the current layout, in the layout before
    "surface": ("surface_steps", "point_steps"),
    "grid": ("grid_steps", "grid"),
    "features": ("feature_steps", "feature_steps"),
    "key points": ("keypoint_steps", "keypoints"),
}


def reencoded(data: bytes) -> bytes:
    """The archive's arrays written again, each member with the method it was written with."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as source, zipfile.ZipFile(buffer, "w") as target:
        for member in source.infolist():
            array = np.lib.format.read_array(io.BytesIO(source.read(member)))
            written = zipfile.ZipInfo(member.filename, date_time=member.date_time)
            written.compress_type = member.compress_type
            with target.open(written, "w") as handle:
                np.lib.format.write_array(handle, array, allow_pickle=False)
    return buffer.getvalue()


def timed(action, runs: int = 3) -> float:
    """The median seconds ``action()`` takes."""
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(library: Path, limit: int | None) -> dict:
    """The row of ``library``'s first ``limit`` entry files."""
    manifest = read_manifest(library)
    ids = manifest.ids[:limit]
    sizes, members, reads, writes, layouts = [], [], [], [], set()
    for model_id in ids:
        data = (library / manifest.entries[model_id].file).read_bytes()
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            compressed = {
                m.filename.removesuffix(".npy"): m.compress_size for m in archive.infolist()
            }
        layout = 0 if "surface_steps" in compressed else 1
        layouts.add(("current", "before")[layout])
        sizes.append(len(data))
        members.append({label: compressed[names[layout]] for label, names in MEMBERS.items()})
        reads.append(timed(lambda data=data: entry_from_arrays(npz_arrays(data))))
        writes.append(timed(lambda data=data: reencoded(data)))
    return {
        "library": f"{library} ({len(ids)} of {len(manifest.entries)})",
        "layout": ", ".join(sorted(layouts)),
        "median KiB": statistics.median(sizes) / 1024,
        "mean KiB": statistics.fmean(sizes) / 1024,
        "largest KiB": max(sizes) / 1024,
        "at most 100 KB": sum(s <= 100_000 for s in sizes) / len(sizes) * 100,
        **{
            f"{label} KiB": statistics.median(m[label] for m in members) / 1024 for label in MEMBERS
        },
        "read ms": statistics.median(reads) * 1000,
        "encode ms": statistics.median(writes) * 1000,
    }


def table(rows: list[dict]) -> str:
    header = list(rows[0])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        cells = [f"{v:.1f}" if isinstance(v, float) else str(v) for v in row.values()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("libraries", nargs="+", type=Path)
    parser.add_argument("--limit", type=int, default=200, help="entries measured per library")
    parser.add_argument("--out", type=Path, default=Path("bench/results/entry_size.md"))
    args = parser.parse_args()
    rows = [measure(library, args.limit) for library in args.libraries]
    notes = (
        f"\n\n{platform.machine()}, load {load_average():.2f}; `at most 100 KB`: share of the "
        "entry files; times are medians of 3 reads and 3 encodes of each entry.\n"
    )
    publish(table(rows) + notes, args.out)


if __name__ == "__main__":
    main()
