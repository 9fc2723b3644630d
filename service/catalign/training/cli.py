"""The training commands of ``catalign``: ``neighbours``, ``train``, ``train-orientation`` and
``calibrate`` (registered on the main command line by :mod:`catalign.cli`). Their defaults are
their configurations' (:mod:`catalign.training.config`), the one source of each value.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from catalign.cli_support import (
    CategoryFolder,
    ChairsFolder,
    FolderUnits,
    TablesFolder,
    exit_on_error,
    options_to,
)
from catalign.errors import ConfigError
from catalign.training.config import (
    CalibrationConfig,
    OrientationConfig,
    RetrievalConfig,
    TrainConfig,
)
from catalign.training.sources import one_category, training_sources

if TYPE_CHECKING:
    pass

TRAIN, ORIENTATION, CALIBRATION = TrainConfig(), OrientationConfig(), CalibrationConfig()
RETRIEVAL = RetrievalConfig()


def neighbours(
    k: Annotated[int, typer.Option(min=1, help="Neighbours per shape.")] = 3,
    chairs_dir: ChairsFolder = None,
) -> None:
    """Print each shared chair's nearest training chairs by EMD in NCC (cached on disk)."""
    from catalign.data.neighbours import shape_neighbours
    from catalign.data.shapes import SharedChairs

    with exit_on_error():
        chairs = SharedChairs(chairs_dir)
        shapes = {i: chairs.load(i).points for i in chairs.ids()}
    result = shape_neighbours(shapes, chairs.ids("train"), k=k)
    for shape_id, near in result.items():
        typer.echo(f"{shape_id}: " + ", ".join(f"{n} ({d:.4f})" for n, d in near))


def train(
    out: Annotated[
        Path, typer.Option(help="Run folder: state, CSV log, final weights.")
    ] = TRAIN.out,
    model: Annotated[
        str | None,
        typer.Option(
            help=f"ResUNetBN2C or ResUNetSmall (default: the --init-from weights', else "
            f"{TRAIN.model})."
        ),
    ] = None,
    curriculum: Annotated[
        str, typer.Option(help="ncc (the paper's) or same-only (the FCGF ablation).")
    ] = TRAIN.curriculum,
    loss: Annotated[
        str, typer.Option(help="hardest (FCGF) or contrastive (random negatives).")
    ] = TRAIN.loss,
    stage1_steps: Annotated[
        int, typer.Option(min=0, help="Same-instance steps.")
    ] = TRAIN.stage1_steps,
    stage2_steps: Annotated[
        int, typer.Option(min=0, help="Curriculum stage-2 steps.")
    ] = TRAIN.stage2_steps,
    batch_size: Annotated[int, typer.Option(min=1, help="Pairs per step.")] = TRAIN.batch_size,
    voxel_size: Annotated[
        float | None,
        typer.Option(
            help="Voxel size in metres, recorded in the model card (default: the --init-from "
            f"weights', else {TRAIN.voxel_size})."
        ),
    ] = None,
    rotation: Annotated[
        str,
        typer.Option(
            help="Augmentation: upright (any yaw), yaw-bin (+-22.5 deg, 8 query headings), "
            "yaw-quarter (+-45 deg, 4 headings) or so3."
        ),
    ] = TRAIN.rotation,
    procedural: Annotated[
        int, typer.Option(min=0, help="Procedural chairs to add.")
    ] = TRAIN.procedural,
    view_so3_share: Annotated[
        float,
        typer.Option(
            min=0, max=1, help="Share of views of the chair in any rotation (from below)."
        ),
    ] = TRAIN.view_so3_share,
    learning_rate: Annotated[float, typer.Option(help="Adam learning rate.")] = TRAIN.learning_rate,
    seed: Annotated[int, typer.Option(help="Seed of pairs and initial weights.")] = TRAIN.seed,
    validate_every: Annotated[
        int, typer.Option(min=1, help="Steps between validations.")
    ] = TRAIN.validate_every,
    threads: Annotated[int, typer.Option(min=1, help="torch threads.")] = TRAIN.threads,
    init_from: Annotated[
        Path | None, typer.Option(help="Start from another run's weights (a shared stage 1).")
    ] = TRAIN.init_from,
    category: Annotated[
        list[str] | None,
        typer.Option(
            help="Shared shapes to train on: chair and/or table (repeat the option); with "
            "--data, the category of its files."
        ),
    ] = None,
    data: Annotated[
        Path | None,
        typer.Option(
            help="Your own canonically aligned CAD files (+Y up), trained on instead of the "
            "shared shapes: one category (--category NAME) or one sub-folder per category."
        ),
    ] = TRAIN.data,
    units: Annotated[str, typer.Option(help="Units of the --data files: m, cm or mm.")] = (
        TRAIN.units
    ),
    chairs_dir: ChairsFolder = None,
    tables_dir: TablesFolder = None,
) -> None:
    """Train the feature extractor; an interrupted run continues from its last checkpoint."""
    from catalign.training.loop import train as run_training
    from catalign.training.loop import training_shapes

    with exit_on_error():
        sources = training_sources(category, data, units, chairs_dir, tables_dir)
        inherited = initial_architecture(init_from)
    config = options_to(
        TrainConfig,
        out=out,
        model=model or inherited.get("model", TRAIN.model),
        conv1_kernel_size=inherited.get("conv1_kernel_size", TRAIN.conv1_kernel_size),
        curriculum=curriculum,
        loss=loss,
        stage1_steps=stage1_steps,
        stage2_steps=stage2_steps,
        batch_size=batch_size,
        voxel_size=voxel_size or inherited.get("voxel_size", TRAIN.voxel_size),
        procedural=procedural,
        rotation=rotation,
        view_so3_share=view_so3_share,
        learning_rate=learning_rate,
        seed=seed,
        validate_every=validate_every,
        init_from=init_from,
        threads=threads,
        categories=tuple(sources),
        data=data,
        units=units,
    )
    with exit_on_error():
        shapes, val_ids, categories = training_shapes(config, sources)
        card = run_training(config, shapes, val_ids, categories=categories)
    typer.echo(json.dumps(card["validation"], indent=2))
    typer.echo(f"model written to {out}")


def initial_architecture(init_from: Path | None) -> dict[str, object]:
    """The network and voxel size of the weights a run starts from (read from their card), so
    that ``--init-from model_store`` needs no other option."""
    from catalign.features.weights import CARD_FILE

    if init_from is None:
        return {}
    card_path = init_from / CARD_FILE
    if not init_from.is_dir():
        raise ConfigError(f"--init-from {init_from}: no such folder")
    if not card_path.is_file():
        return {}  # a run still training: its settings are in its state
    training = json.loads(card_path.read_text()).get("training", {})
    return {k: training[k] for k in ("model", "conv1_kernel_size", "voxel_size") if k in training}


def train_orientation(
    out: Annotated[
        Path, typer.Option(help="Run folder: cached views, weights and card.")
    ] = ORIENTATION.out,
    steps: Annotated[int, typer.Option(min=1, help="Optimizer steps.")] = ORIENTATION.steps,
    batch_size: Annotated[
        int, typer.Option(min=1, help="Views per step.")
    ] = ORIENTATION.batch_size,
    views_per_shape: Annotated[
        int, typer.Option(min=1, help="Views rendered per shape.")
    ] = ORIENTATION.views_per_shape,
    procedural: Annotated[
        int, typer.Option(min=0, help="Procedural chairs to add.")
    ] = ORIENTATION.procedural,
    seed: Annotated[
        int, typer.Option(help="Seed of views, samples and initial weights.")
    ] = ORIENTATION.seed,
    threads: Annotated[int, typer.Option(min=1, help="torch threads.")] = ORIENTATION.threads,
    learning_rate: Annotated[
        float, typer.Option(help="Peak learning rate.")
    ] = ORIENTATION.learning_rate,
    up_frame: Annotated[
        str, typer.Option(help="Frame the up network sees a view in: view or principal.")
    ] = ORIENTATION.up_frame,
    init_from: Annotated[
        Path | None, typer.Option(help="Start from another run's weights (a longer schedule).")
    ] = ORIENTATION.init_from,
    networks: Annotated[
        str,
        typer.Option(
            help="Networks to train: both, up or heading (the other keeps --init-from's weights)."
        ),
    ] = ORIENTATION.networks,
    fused_share: Annotated[
        float,
        typer.Option(
            help="Share of views that are reconstructions fused along a camera trajectory."
        ),
    ] = ORIENTATION.fused_share,
    so3_share: Annotated[
        float, typer.Option(help="Share of views rendered in any rotation (the rest upright).")
    ] = ORIENTATION.so3_share,
    up_width: Annotated[
        int | None,
        typer.Option(
            min=1, help="Up network width, if not 16 (afresh where --init-from's has another)."
        ),
    ] = ORIENTATION.up_width,
    category: Annotated[
        str,
        typer.Option(
            help="Category to train on: the shared chairs (with procedural chairs) or tables, "
            "or --data's; a run for another category than chair ships in "
            "model_store/categories/NAME/orientation/."
        ),
    ] = ORIENTATION.category,
    data: CategoryFolder = ORIENTATION.data,
    units: FolderUnits = ORIENTATION.units,
    chairs_dir: ChairsFolder = None,
    tables_dir: TablesFolder = None,
) -> None:
    """Train the orientation proposal networks (up and heading) on views of training shapes."""
    from catalign.features.orientation import CARD_FILE, WEIGHTS_FILE
    from catalign.training.orientation import run

    config = options_to(
        OrientationConfig,
        out=out,
        steps=steps,
        batch_size=batch_size,
        views_per_shape=views_per_shape,
        procedural=procedural,
        seed=seed,
        threads=threads,
        learning_rate=learning_rate,
        up_frame=up_frame,
        init_from=init_from,
        networks=networks,
        fused_share=fused_share,
        so3_share=so3_share,
        up_width=up_width,
        category=category,
        data=data,
        units=units,
    )
    with exit_on_error():
        shapes = one_category(category, data, units, chairs_dir, tables_dir)
        card = run(config, shapes)
    typer.echo(json.dumps(card["held_out_accuracy"], indent=2))
    target = "" if config.category == "chair" else f"categories/{config.category}/"
    typer.echo(
        f"orientation model written to {out} (ship it: copy its {WEIGHTS_FILE} and "
        f"{CARD_FILE} to model_store/{target}orientation/)"
    )


def train_retrieval(
    out: Annotated[
        Path, typer.Option(help="Folder of the retrieval encoders (ships in model_store/).")
    ] = RETRIEVAL.out,
    steps: Annotated[int, typer.Option(min=1, help="Training steps.")] = RETRIEVAL.steps,
    procedural: Annotated[
        int, typer.Option(min=0, help="Procedural chairs among the training models.")
    ] = RETRIEVAL.procedural,
    learning_rate: Annotated[
        float, typer.Option(min=0.0, help="Adam's learning rate (cosine decay to 0).")
    ] = RETRIEVAL.learning_rate,
    hard_negatives: Annotated[
        int, typer.Option(min=0, help="Models each view is nearest to, added as negatives.")
    ] = RETRIEVAL.hard_negatives,
    init_from: Annotated[
        Path | None,
        typer.Option(help="Encoders to start from, e.g. model_store/retrieval (default: none)."),
    ] = RETRIEVAL.init_from,
    seed: Annotated[int, typer.Option(help="Seed of the views and the training.")] = RETRIEVAL.seed,
    threads: Annotated[int, typer.Option(min=1, help="torch threads.")] = RETRIEVAL.threads,
    model_dir: Annotated[
        Path | None,
        typer.Option(help="Feature weights the encoders sit on (default: model_store/)."),
    ] = None,
    chairs_dir: ChairsFolder = None,
    tables_dir: TablesFolder = None,
) -> None:
    """Train the retrieval encoders: a partial view's descriptor next to its own model's."""
    import torch

    from catalign.features.extractor import LearnedExtractor
    from catalign.features.retrieval import CARD_FILE, WEIGHTS_FILE
    from catalign.training.retrieval import run

    config = options_to(RetrievalConfig, out=out, steps=steps, procedural=procedural,
                        learning_rate=learning_rate, hard_negatives=hard_negatives,
                        init_from=init_from, seed=seed, threads=threads)  # fmt: skip
    with exit_on_error():
        sources = training_sources(["chair", "table"], None, "m", chairs_dir, tables_dir)
        extractor = LearnedExtractor(model_dir)
        torch.set_num_threads(config.threads)
        card = run(config, list(sources.values()), extractor)
    typer.echo(json.dumps(card["held_out"], indent=2))
    typer.echo(
        f"retrieval encoders written to {out} (ship them: copy {WEIGHTS_FILE} and {CARD_FILE} "
        "to model_store/retrieval/, then run `catalign library redescribe DIR` on every library)"
    )


def calibrate(
    out: Annotated[
        Path, typer.Option(help="Folder of the calibrator (ships in model_store/).")
    ] = CALIBRATION.out,
    views: Annotated[
        int, typer.Option(min=0, help="Single views per training chair and mode.")
    ] = CALIBRATION.views,
    fused_views: Annotated[
        int,
        typer.Option(
            min=0, help="Reconstructions (fused views, cut out loosely) per chair and mode."
        ),
    ] = CALIBRATION.fused_views,
    seed: Annotated[int, typer.Option(help="Seed of the views and of RANSAC.")] = CALIBRATION.seed,
    pose_mode: Annotated[
        list[str] | None,
        typer.Option(help="upright (up given) and/or so3 (no up); repeat; both if unset."),
    ] = None,
    max_shapes: Annotated[
        int | None, typer.Option(min=2, help="Cap on training chairs (quick runs).")
    ] = None,
    model_dir: Annotated[
        Path | None,
        typer.Option(help="Weights whose answers are calibrated (default: model_store/)."),
    ] = None,
    category: Annotated[
        str,
        typer.Option(
            help="Category whose answers are calibrated: the shared chairs or tables, or "
            "--data's (another category than chair ships in "
            "model_store/categories/NAME/confidence/)."
        ),
    ] = CALIBRATION.category,
    data: CategoryFolder = CALIBRATION.data,
    units: FolderUnits = CALIBRATION.units,
    chairs_dir: ChairsFolder = None,
    tables_dir: TablesFolder = None,
    samples: Annotated[
        list[Path] | None,
        typer.Option(
            help="Refit from runs' samples.npz (repeat to join runs) instead of registering views."
        ),
    ] = None,
) -> None:
    """Fit the answers' confidence (boosted trees) on views of the training shapes."""
    from catalign.features.extractor import LearnedExtractor
    from catalign.training.calibration import run

    modes = tuple(pose_mode or ("upright", "so3"))
    with exit_on_error():
        for mode in modes:
            if mode not in ("upright", "so3"):
                raise ConfigError(f"unknown pose mode {mode!r}; use upright or so3")
        if views + fused_views == 0 and not samples:
            raise ConfigError("--views and --fused-views are both 0: there is nothing to fit on")
        config = CalibrationConfig(
            out=out,
            views=views,
            fused_views=fused_views,
            seed=seed,
            pose_modes=modes,
            max_shapes=max_shapes,  # type: ignore[arg-type]
            category=category,
            data=data,
            units=units,
        )
        # A refit from saved samples needs no weights (nor their current calibrator).
        extractor = None if samples else LearnedExtractor(model_dir)
        shapes = one_category(category, data, units, chairs_dir, tables_dir)
        calibrator = run(config, shapes, extractor, samples_files=samples or ())
    typer.echo(json.dumps(calibrator.card["in_sample"], indent=2))
    typer.echo(f"calibrator written to {out}")
