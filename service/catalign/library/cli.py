"""``catalign library ...``: build, extend, prune, inspect and convert CAD library indexes.

Every command takes ``--model-dir`` (the feature extractor's weights, default ``model_store/``)
where features are computed; an error the library detects prints one sentence, exit code 2.
"""

from __future__ import annotations

import os
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import typer

from catalign.cli_support import EngineOptions, exit_on_error

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="Build, extend, prune, inspect and convert CAD libraries.",
)

ModelDir = Annotated[Path | None, typer.Option(help="Extractor weights (default: model_store/).")]
Workers = Annotated[
    int | None,
    typer.Option(min=1, help="Processes describing the models (default: one per core)."),
]
Units = Annotated[str, typer.Option(help="Units of the source coordinates: m, cm or mm.")]
Category = Annotated[
    str | None,
    typer.Option(
        help="Category of every model (a short lower-case name: chair, table). Without it, a "
        "file in a sub-folder of a named folder takes the sub-folder's name (SRC/table/a.ply: "
        "table), any other file is a chair."
    ),
]


def _extractor(model_dir: Path | None):
    from catalign.features.extractor import LearnedExtractor

    return LearnedExtractor(model_dir)


@app.command()
def build(
    sources: Annotated[list[Path], typer.Argument(help="Shape files and folders.")],
    out: Annotated[Path, typer.Option(help="Library folder to create.")],
    units: Units = "m",
    category: Category = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing library.")] = False,
    model_dir: ModelDir = None,
    workers: Workers = None,
) -> None:
    """Build a library from meshes and point clouds (model id = file stem); run it again
    after an interruption to resume where it stopped."""
    from catalign.library.index import build as build_index

    started = time.perf_counter()
    with exit_on_error():
        manifest = build_index(
            sources,
            out,
            _extractor(model_dir),
            units=units,
            category=category,
            overwrite=overwrite,
            workers=workers or os.cpu_count() or 1,
        )
    typer.echo(
        f"built {out}: {len(manifest.entries)} models ({_counts(manifest.categories())}) "
        f"{_rate(len(manifest.entries), started)}"
    )


@app.command()
def procedural(
    out: Annotated[Path, typer.Option(help="Library folder to create.")],
    count: Annotated[int, typer.Option(min=1, help="Number of procedural chairs.")] = 60,
    first_seed: Annotated[int, typer.Option(min=0, help="Seed of the first chair.")] = 0,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing library.")] = False,
    model_dir: ModelDir = None,
    workers: Workers = None,
) -> None:
    """Build a library of procedural chairs (the shipped default library)."""
    from catalign.library.index import build_procedural

    started = time.perf_counter()
    with exit_on_error():
        manifest = build_procedural(
            out,
            _extractor(model_dir),
            count,
            first_seed,
            overwrite=overwrite,
            workers=workers or os.cpu_count() or 1,
        )
    typer.echo(
        f"built {out}: {len(manifest.entries)} procedural chairs "
        f"{_rate(len(manifest.entries), started)}"
    )


def _rate(count: int, started: float) -> str:
    """How long the command took and how many entries per second that makes (resumed ones
    count as done)."""
    elapsed = time.perf_counter() - started
    return f"in {elapsed:.0f} s ({count / max(elapsed, 1e-9):.1f} per second)"


@app.command()
def add(
    library: Annotated[Path, typer.Argument(help="Library folder.")],
    sources: Annotated[list[Path], typer.Argument(help="Shape files and folders to add.")],
    units: Units = "m",
    category: Category = None,
    replace: Annotated[bool, typer.Option(help="Replace entries whose id exists.")] = False,
    model_dir: ModelDir = None,
) -> None:
    """Add models to a library without rebuilding it."""
    from catalign.library.index import add as add_entries
    from catalign.library.store import category_counts

    with exit_on_error():
        add_entries(
            library,
            sources,
            _extractor(model_dir),
            units=units,
            category=category,
            replace=replace,
        )
        counts = category_counts(library)
    typer.echo(f"{library}: {sum(counts.values())} models ({_counts(counts)})")


@app.command()
def remove(
    library: Annotated[Path, typer.Argument(help="Library folder.")],
    ids: Annotated[list[str], typer.Argument(help="Model ids to remove.")],
) -> None:
    """Remove models from a library."""
    from catalign.library.index import remove as remove_entries

    with exit_on_error():
        left = remove_entries(library, ids)
    typer.echo(f"{library}: {left} models")


@app.command()
def configure(
    library: Annotated[Path, typer.Argument(help="Library folder.")],
    engine: EngineOptions = None,
    clear: Annotated[
        bool, typer.Option(help="Drop the options the library had before setting these.")
    ] = False,
) -> None:
    """Set the engine options a server runs this library with (CATALIGN_ENGINE__* variables
    and `catalign serve --engine` still override them)."""
    from catalign.library.index import configure as configure_library
    from catalign.registration.config import parse_options, stored_options

    with exit_on_error():
        options = parse_options(engine or ()).model_dump(exclude_unset=True)
        stored = configure_library(library, options, clear=clear, combine=stored_options)
    typer.echo(f"{library}: engine options {_options(stored)}")


@app.command("list")
def list_command(library: Annotated[Path, typer.Argument(help="Library folder.")]) -> None:
    """Print the model ids, one per line."""
    from catalign.library.index import list_models

    with exit_on_error():
        ids = list_models(library)
    typer.echo("\n".join(ids))


@app.command()
def info(library: Annotated[Path, typer.Argument(help="Library folder.")]) -> None:
    """Print the catalogue's summary: format, extractor, dates, size."""
    from catalign.library.index import info as read_info
    from catalign.library.shortlist_index import index_status

    with exit_on_error():
        manifest = read_info(library)
    typer.echo(
        f"library: {library}\nformat: {manifest.format_version}\n"
        f"extractor: {manifest.fingerprint} (voxel {manifest.voxel_size} m)\n"
        f"created: {manifest.created}\nupdated: {manifest.updated}\n"
        f"models: {len(manifest.entries)}\n"
        f"categories: {_counts(manifest.categories()) or '(none)'} "
        f"(default {manifest.category})\nsymmetric about up: {_symmetric(manifest)}\n"
        f"engine options: {_options(manifest.engine)}\n"
        f"shortlist index: {index_status(library, manifest.entries)}"
    )


@app.command()
def index(
    library: Annotated[Path, typer.Argument(help="Library folder.")],
    threads: Annotated[
        int | None, typer.Option(min=1, help="Threads building the graphs (default: every core).")
    ] = None,
) -> None:
    """Write the shortlist's index again over every entry: the entries added or described
    again since it was written are found by an exact scan until then. Builds write it
    themselves, and so does an add once more than 1,000 entries (or a tenth) wait; serving
    processes load the library again with it."""
    from catalign.library.index import reindex

    with exit_on_error(), _entries_bar(f"indexing {library.name}") as advance:
        written = reindex(library, threads or 0, advance)
    typer.echo(
        f"{library}: shortlist index of {written.entries} models "
        f"({_counts(written.categories) or 'none'}) in {written.seconds:.1f} s"
    )


@app.command()
def migrate(
    library: Annotated[Path, typer.Argument(help="Library folder of an older format.")],
) -> None:
    """Convert a library of an older format (2: manifest.json, 3: catalogue.sqlite with full
    entries) in place: every entry rewritten small, no features computed again (no weights
    needed), a new catalogue.sqlite. In a library of the current format, rewrite the entries
    of the earlier, larger layout and give records written before outlines theirs. Safe to
    interrupt and run again."""
    from catalign.library.legacy import format_of
    from catalign.library.legacy import migrate as migrate_library
    from catalign.library.records import FORMAT_VERSION
    from catalign.library.store import read_manifest

    with exit_on_error():
        before = format_of(library) if library.is_dir() else None
        files = outlined = None
        if before == FORMAT_VERSION:
            records = read_manifest(library).entries
            files = {i: r.file for i, r in records.items()}
            outlined = {i for i, r in records.items() if r.outline}
        with _entries_bar(f"converting {library.name}") as advance:
            manifest = migrate_library(library, advance)
    if files is not None:
        rewritten = sum(files.get(i) != r.file for i, r in manifest.entries.items())
        done = f"already of format {FORMAT_VERSION}"
        if rewritten:
            done += f", {rewritten} entries of the earlier layout rewritten"
        given = sum(
            i not in outlined and files.get(i) == r.file for i, r in manifest.entries.items()
        )
        if given:
            done += f", {given} outlines added"
    else:
        done = f"converted from format {before} to format {FORMAT_VERSION}"
    typer.echo(f"{library}: {done}, {len(manifest.entries)} models")


@app.command()
def redescribe(
    library: Annotated[Path, typer.Argument(help="Library folder.")],
    model_dir: ModelDir = None,
) -> None:
    """Give a library the shortlisting descriptors of new retrieval encoders (over the same
    feature weights), from its own entries: no source file is read, no feature computed again.
    Safe to interrupt and run again."""
    from catalign.library.redescribe import redescribe as redescribe_library
    from catalign.library.store import read_manifest

    with exit_on_error():
        extractor = _extractor(model_dir)
        before = read_manifest(library).fingerprint
        with _entries_bar(f"describing {library.name}") as advance:
            manifest = redescribe_library(library, extractor, advance)
    done = "already described by" if before == manifest.fingerprint else "now described by"
    typer.echo(f"{library}: {len(manifest.entries)} models {done} {manifest.fingerprint}")


@contextmanager
def _entries_bar(description: str) -> Iterator[Callable[[int, int], None]]:
    """A progress bar over a library's entries, advanced by the (done, total) callback that
    conversions and re-descriptions call after each entry."""
    from tqdm import tqdm

    with tqdm(desc=description, unit="entry", disable=None) as bar:

        def advance(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        yield advance


def _symmetric(manifest: Any) -> str:
    """``12 (half turn 9, quarter turn 2, any turn 1)``: the entries that look the same
    turned about their up, by symmetry order."""
    names = {0: "any turn", 2: "half turn", 4: "quarter turn"}
    orders = Counter(record.symmetry for record in manifest.entries.values())
    unknown = orders.pop(None, 0)
    orders.pop(1, None)
    parts = [f"{names.get(order, f'order {order}')} {n}" for order, n in sorted(orders.items())]
    text = f"{sum(orders.values())}" + (f" ({', '.join(parts)})" if parts else "")
    return text + (f", {unknown} not yet known (found when loaded)" if unknown else "")


def _counts(counts: dict[str, int]) -> str:
    """``chair 60, table 12``: the entries of each category."""
    return ", ".join(f"{name} {count}" for name, count in counts.items())


def _options(engine: dict[str, Any], prefix: str = "") -> str:
    """``decision.alternatives=0 top_k=2``: the options a library sets, by their dotted names."""
    parts = [
        _options(value, f"{prefix}{name}.")
        if isinstance(value, dict)
        else f"{prefix}{name}={value}"
        for name, value in sorted(engine.items())
    ]
    return " ".join(parts) or ("" if prefix else "(the defaults)")
