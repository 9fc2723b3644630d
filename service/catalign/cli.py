"""Command-line front door: ``catalign evaluate|train|neighbours|serve|library ...``.

Errors that catalign raises on purpose are shown as one sentence with exit code 2; anything else
is a bug and keeps its traceback.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from catalign.cli_support import EngineOptions, exit_on_error
from catalign.errors import ConfigError
from catalign.library.cli import app as library_app
from catalign.training.cli import (
    calibrate,
    neighbours,
    train,
    train_orientation,
    train_retrieval,
)

if TYPE_CHECKING:
    from catalign.registration.config import EngineConfig

app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)
app.add_typer(library_app, name="library")


@app.callback()
def main(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log at INFO level.")] = False,
) -> None:
    """catalign: align partial point clouds of chairs to a CAD library."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


@app.command()
def evaluate(
    method: Annotated[
        str, typer.Option(help="Registration method: fpfh, learned or fpfh-engine.")
    ] = "fpfh",
    model_dir: Annotated[
        Path | None, typer.Option(help="Weights of the learned method (default: model_store/).")
    ] = None,
    setting: Annotated[
        list[str] | None, typer.Option(help="same and/or cross (repeat the option); both if unset.")
    ] = None,
    views: Annotated[
        str,
        typer.Option(
            help="Views of each validation shape: single or fused (a reconstruction fused from a "
            "camera trajectory), with :N views per shape (fused:4); a bare N is N single views.",
        ),
    ] = "single:2",
    max_shapes: Annotated[
        int | None,
        typer.Option(min=1, help="Cap on observed shapes and on each library (quick runs)."),
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the test cases and of RANSAC.")] = 0,
    pose_mode: Annotated[
        str,
        typer.Option(
            help="upright (yaw only), so3 (the chair in any rotation) or turned (the upright "
            "view turned at random: a sensor without IMU)."
        ),
    ] = "upright",
    chairs_dir: Annotated[
        Path | None, typer.Option(help="Shared chairs folder (default: ../shared/data/chairs).")
    ] = None,
    up_prior: Annotated[
        bool | None,
        typer.Option(
            "--up-prior/--no-up-prior",
            help="Tell the method that world +Z is up (default: on for upright only).",
        ),
    ] = None,
    up_error: Annotated[
        float,
        typer.Option(
            min=0.0,
            max=90.0,
            help="Tilt the up the method is told by this many degrees (an imprecise IMU).",
        ),
    ] = 0.0,
    floor: Annotated[
        bool,
        typer.Option(
            "--floor/--no-floor",
            help="Keep a ring of floor around each chair, as a segmentation that kept some floor "
            "would; the chair stands on it, and with so3 the whole view is turned at random.",
        ),
    ] = False,
    table: Annotated[
        bool,
        typer.Option(
            "--table/--no-table",
            help="Push each chair under a table whose top hides what lies beneath it; with so3 "
            "the whole view is turned at random.",
        ),
    ] = False,
    category: Annotated[
        str, typer.Option(help="Shared shapes to evaluate on: chair or table.")
    ] = "chair",
    tables_dir: Annotated[
        Path | None, typer.Option(help="Shared tables folder (default: ../shared/data/tables).")
    ] = None,
    out: Annotated[Path | None, typer.Option(help="JSON report path.")] = None,
    engine: EngineOptions = None,
) -> None:
    """Run a registration method on the validation split and print the paper's table."""
    from catalign.data.shapes import shared_shapes
    from catalign.evaluation.protocol import VIEW_MODES, parse_views
    from catalign.evaluation.runner import EvaluationConfig, evaluate, write_report
    from catalign.registration.config import parse_options
    from catalign.registration.methods import check_method

    settings = tuple(setting or ("same", "cross"))
    with exit_on_error():
        engine_config = None if engine is None else parse_options(engine)
        check_method(method, engine_config)  # fails before any data is read
        for name in settings:
            if name not in ("same", "cross"):
                raise ConfigError(f"unknown setting {name!r}; use same or cross")
        if category not in ("chair", "table"):
            raise ConfigError(f"unknown category {category!r}; the shared shapes are chair, table")
        if pose_mode not in VIEW_MODES:
            raise ConfigError(f"unknown pose mode {pose_mode!r}; use upright, so3 or turned")
        view_source, views_per_shape = parse_views(views)
        up_given = (pose_mode == "upright") if up_prior is None else up_prior
        if up_error and not up_given:
            raise ConfigError("--up-error tilts the up the method is told: it needs --up-prior")
        config = EvaluationConfig(
            method=method,
            settings=settings,  # type: ignore[arg-type]
            views=views_per_shape,
            source=view_source,
            max_shapes=max_shapes,
            seed=seed,
            pose_mode=pose_mode,  # type: ignore[arg-type]
            model_dir=model_dir,
            up_prior=up_given,
            up_error_deg=up_error,
            floor=floor,
            table=table,
            engine=engine_config,
            category=category,
        )
        source = shared_shapes(category, chairs_dir if category == "chair" else tables_dir)
        report = evaluate(config, source)
    prior = ("" if config.up_prior else "-no-up") + (f"-up-error{up_error:g}" if up_error else "")
    kept = ("-floor" if floor else "") + ("-table" if table else "")
    kept += "-fused" if view_source == "fused" else ""
    of = "" if category == "chair" else f"-{category}"
    path = out or Path("results") / f"evaluate-{method}{of}-{pose_mode}{prior}{kept}.json"
    write_report(report, path)
    typer.echo(report["table"])
    typer.echo(f"\nreport written to {path}")


# The training commands live beside the training code (catalign.training.cli).
app.command()(neighbours)
app.command()(train)
app.command("train-orientation")(train_orientation)
app.command("train-retrieval")(train_retrieval)
app.command()(calibrate)


@app.command()
def serve(
    library: Annotated[
        Path | None, typer.Option(help="Library folder (default model_store/library).")
    ] = None,
    model_dir: Annotated[
        Path | None, typer.Option(help="Extractor weights (default model_store/).")
    ] = None,
    host: Annotated[str | None, typer.Option(help="Address to listen on (default 127.0.0.1).")] = (
        None
    ),
    port: Annotated[int | None, typer.Option(help="HTTP port (default 8000).")] = None,
    grpc_port: Annotated[
        int | None, typer.Option(help="gRPC port, 0 disables gRPC (default 50051).")
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Registration workers (default 2), each a process with its own engine "
            "(CATALIGN_WORKER_PROCESSES=false: threads sharing one)."
        ),
    ] = None,
    queue: Annotated[
        int | None, typer.Option(help="Requests that may wait for a worker (default 8).")
    ] = None,
    api_key: Annotated[
        str | None,
        typer.Option(
            help="Require this X-API-Key; it shows in `ps`, so prefer --api-key-file or the "
            "CATALIGN_API_KEY variable."
        ),
    ] = None,
    api_key_file: Annotated[
        Path | None,
        typer.Option(help="Require the X-API-Key held in this file's first line."),
    ] = None,
    read_only: Annotated[
        bool | None, typer.Option("--read-only", help="Refuse library changes.")
    ] = None,
    engine: EngineOptions = None,
) -> None:
    """Serve registration over HTTP (FastAPI on uvicorn) and gRPC.

    Every setting can also come from a CATALIGN_* environment variable (CATALIGN_PORT,
    CATALIGN_MAX_POINTS, CATALIGN_ENGINE__TOP_K, ...; see catalign.api.settings); flags
    override them, --engine options field by field (those in effect: engine at GET /info).
    """
    import uvicorn
    from pydantic import ValidationError

    from catalign.api.app import create_app
    from catalign.api.settings import ServiceSettings
    from catalign.registration.config import parse_options
    from catalign.threads import limit_malloc_arenas

    flags = {
        "library": library,
        "model_dir": model_dir,
        "host": host,
        "port": port,
        "grpc_port": grpc_port,
        "workers": workers,
        "queue": queue,
        "api_key": api_key,
        "api_key_file": api_key_file,
        "read_only": read_only,
    }
    try:
        settings = ServiceSettings(**{k: v for k, v in flags.items() if v is not None})
    except ValidationError as error:
        first = error.errors()[0]
        if first["loc"]:
            name = str(first["loc"][0])
            variable = "CATALIGN_" + "__".join(map(str, first["loc"])).upper()
            option = f"--{name.replace('_', '-')}" if name in flags else variable
            typer.echo(f"error: {option}: {first['msg']}", err=True)
        else:  # a check across settings (the API key given twice, an unreadable key file)
            typer.echo(f"error: {first['msg'].removeprefix('Value error, ')}", err=True)
        raise typer.Exit(code=2) from None
    with exit_on_error():
        if engine:  # over the CATALIGN_ENGINE__* variables, field by field
            merged = parse_options(engine, base=settings.engine)
            settings = settings.model_copy(update={"engine": merged})
        _check_serve_paths(settings.model_dir, settings.library, settings.engine)
    logging.getLogger().setLevel(settings.log_level.upper())
    limit_malloc_arenas(2)
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_config=None,
        access_log=False,  # the app logs one line per request, with its request id
        timeout_graceful_shutdown=30,
    )


def _check_serve_paths(model_dir: Path, library: Path, engine: EngineConfig) -> None:
    """Fail in one sentence before start-up when the weights or the library are missing, when
    the library was built with other weights (or other retrieval encoders), or when its engine
    options are not valid ones."""
    from catalign.features.extractor import fingerprint_in
    from catalign.features.weights import CARD_FILE, WEIGHTS_FILE
    from catalign.library.index import info
    from catalign.library.loaded import check_fingerprint
    from catalign.registration.config import served_config

    if not (model_dir / WEIGHTS_FILE).is_file() or not (model_dir / CARD_FILE).is_file():
        raise ConfigError(
            f"no trained weights in {model_dir} (expected {WEIGHTS_FILE} and {CARD_FILE}); "
            "pass --model-dir or train one with `catalign train`"
        )
    catalogue = info(library)
    check_fingerprint(catalogue, fingerprint_in(model_dir), library)
    try:
        served_config(engine, catalogue.engine)
    except ConfigError as error:
        raise ConfigError(
            f"the library {library} sets {error}; set its options again with "
            f"`catalign library configure {library} --clear [--engine FIELD=VALUE ...]`"
        ) from None
