"""The training loop: curriculum over pair kinds, loss, validation, resumable checkpoints.

``train`` reads like the method: load shapes and their EMD neighbours, build the sampler and
the fixed validation pairs, then for each step draw a batch of pairs (same-instance in stage 1;
mostly cross-instance in stage 2 of the ``ncc`` curriculum), run the network once, apply the
loss and step the optimizer. Every ``checkpoint_every`` steps the state is saved, so a killed
run continues where it stopped; every ``validate_every`` steps MatchAcc and FMR are logged.
"""

from __future__ import annotations

import csv
import json
import logging
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from tqdm import tqdm

from catalign.data.neighbours import shape_neighbours
from catalign.data.shapes import ProceduralChairs, Shape, Split
from catalign.errors import ConfigError
from catalign.features.orientation import ORIENTATION_DIR
from catalign.features.resunet import build_model
from catalign.paths import CATEGORIES_DIR
from catalign.registration.decision.confidence import CALIBRATION_DIR
from catalign.training.batches import pair_features
from catalign.training.checkpoint import (
    CARD_FILE,
    STATE_FILE,
    WEIGHTS_FILE,
    export_model,
    load_state,
    save_state,
)
from catalign.training.config import TrainConfig
from catalign.training.loss import contrastive_loss, hardest_contrastive_loss
from catalign.training.pairs import PairKind, PairSample, PairSampler
from catalign.training.validation import validate

log = logging.getLogger(__name__)
LOSSES = {"contrastive": contrastive_loss, "hardest": hardest_contrastive_loss}
LOG_COLUMNS = (
    "step",
    "kind",
    "loss",
    "pos",
    "neg",
    "pairs_per_s",
    "elapsed_s",
    "same_match_acc",
    "same_fmr",
    "cross_match_acc",
    "cross_fmr",
)


class ShapeSource(Protocol):
    """Shapes of one category by id (the shared chairs or tables, a user's CAD folder)."""

    category: str

    def ids(self, split: Split | None = None) -> list[str]: ...

    def metric(self, shape_id: str) -> Shape: ...


def training_shapes(
    config: TrainConfig, sources: ShapeSource | Mapping[str, ShapeSource]
) -> tuple[dict[str, Shape], list[str], dict[str, str]]:
    """Metric training shapes (the shared shapes of every source, each at a height of its
    category, plus procedural chairs), the validation ids and each shape's category."""
    if not isinstance(sources, Mapping):
        sources = {sources.category: sources}
    shapes: dict[str, Shape] = {}
    categories: dict[str, str] = {}
    val_ids: list[str] = []
    for category, source in sources.items():
        shapes |= {i: source.metric(i) for i in source.ids()}
        categories |= dict.fromkeys(source.ids(), category)
        val_ids += source.ids("val")
    procedural = {s.shape_id: s for s in ProceduralChairs(config.procedural)}
    shapes |= procedural
    categories |= dict.fromkeys(procedural, "chair")
    return shapes, val_ids, categories


def neighbours_within_categories(
    shapes: dict[str, Shape], train_ids: list[str], categories: Mapping[str, str]
) -> dict[str, list[tuple[str, float]]]:
    """Each shape's 3 nearest training shapes of its own category (EMD in NCC, cached)."""
    near: dict[str, list[tuple[str, float]]] = {}
    for category in sorted(set(categories.values())):
        members = {i: s.points for i, s in shapes.items() if categories[i] == category}
        near |= shape_neighbours(members, [i for i in train_ids if i in members], k=3)
    return near


def pair_kind(config: TrainConfig, step: int, rng: np.random.Generator) -> PairKind:
    """The curriculum: same-instance first, then cross-instance with a share of same kept."""
    if config.curriculum == "same-only" or step < config.stage1_steps:
        return "same"
    return "same" if rng.random() < config.same_share else "cross"


def validation_pairs(
    sampler: PairSampler, val_ids: list[str], count: int, seed: int
) -> list[PairSample]:
    """A fixed set of same- and cross-instance pairs on validation shapes."""
    pairs = []
    for k in range(count):
        rng = np.random.default_rng([seed, 10**6, k])
        kind: PairKind = "same" if k % 2 == 0 else "cross"
        pairs.append(sampler.sample(kind, val_ids[(k // 2) % len(val_ids)], rng))
    return pairs


def train(
    config: TrainConfig,
    shapes: dict[str, Shape],
    val_ids: list[str],
    progress: bool = True,
    categories: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """Train (or resume) a feature extractor on ``shapes`` less ``val_ids`` (metric shapes in
    the canonical frame); export the final weights and model card. ``categories`` gives each
    shape's category (all chairs without it): a cross-instance pair takes its NCC positives
    between shapes of one category, nearest neighbours by EMD within it."""
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    train_ids = sorted(set(shapes) - set(val_ids))
    categories = categories or dict.fromkeys(shapes, "chair")
    near = neighbours_within_categories(shapes, train_ids, categories)
    sampler = PairSampler(
        shapes,
        {i: [n for n, _ in v] for i, v in near.items()},
        voxel_size=config.voxel_size,
        tau_ncc=config.tau_ncc,
        rotation=config.rotation,
        view_so3_share=config.view_so3_share,
    )
    val_pairs = validation_pairs(sampler, val_ids, config.validation_pairs, config.seed)
    taus = {"same": sampler.tau, "cross": sampler.tau_ncc}

    model = build_model(config.model, conv1_kernel_size=config.conv1_kernel_size)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    start = _resume(config, model, optimizer)
    if start == 0 and config.init_from is not None:
        try:
            model.load_state_dict(_initial_weights(config.init_from))
        except RuntimeError:
            raise ConfigError(
                f"--init-from {config.init_from} holds weights of another network than "
                f"{config.model} (kernel {config.conv1_kernel_size}); pass its --model"
            ) from None
    loss_fn = LOSSES[config.loss]
    log_path = config.out / "log.csv"
    _truncate_log(log_path, start)
    started = time.perf_counter()
    elapsed_before = _elapsed_before(log_path)

    model.train()
    bar = tqdm(total=config.total_steps, initial=start, desc="train", disable=not progress)
    metrics: dict[str, float] = {}
    for step in range(start, config.total_steps):
        rng = np.random.default_rng([config.seed, step])
        tick = time.perf_counter()
        samples = [
            sampler.sample(pair_kind(config, step, rng), str(rng.choice(train_ids)), rng)
            for _ in range(config.batch_size)
        ]
        generator = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
        terms = [
            loss_fn(
                fa,
                fb,
                torch.from_numpy(s.positives),
                torch.from_numpy(s.a.aligned).float(),
                torch.from_numpy(s.b.aligned).float(),
                s.neg_radius,
                generator,
            )
            for s, (fa, fb) in zip(samples, pair_features(model, samples), strict=True)
            if len(s.positives)
        ]
        if terms:
            loss = torch.stack([t.loss for t in terms]).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        row = {
            "step": step + 1,
            "kind": "+".join(sorted({s.kind for s in samples})),
            "loss": float(loss.detach()) if terms else float("nan"),
            "pos": float(np.mean([t.pos_distance for t in terms])) if terms else float("nan"),
            "neg": float(np.nanmean([t.neg_distance for t in terms])) if terms else float("nan"),
            "pairs_per_s": len(samples) / (time.perf_counter() - tick),
            "elapsed_s": elapsed_before + time.perf_counter() - started,
        }
        if (step + 1) % config.validate_every == 0 or step + 1 == config.total_steps:
            metrics = validate(model, val_pairs, taus)
            row |= metrics
            log.info("step %d validation %s", step + 1, metrics)
        _append_csv(log_path, row)
        bar.set_postfix(
            loss=f"{row['loss']:.3f}",
            pos=f"{row['pos']:.2f}",
            neg=f"{row['neg']:.2f}",
            pps=f"{row['pairs_per_s']:.1f}",
        )
        bar.update()
        if (step + 1) % config.checkpoint_every == 0 or step + 1 == config.total_steps:
            save_state(config.out, model, optimizer, step + 1, _plain(config))
    bar.close()

    if not metrics:
        metrics = validate(model, val_pairs, taus)
    card = {
        "training": _plain(config),
        "training_data": {
            "shared_train_chairs": len(
                [i for i in train_ids if not i.startswith("proc-") and categories[i] == "chair"]
            ),
            "procedural_chairs": config.procedural,
            "validation_chairs": len(val_ids),
            "categories": {
                name: sum(categories[i] == name for i in train_ids)
                for name in sorted(set(categories.values()))
            },
        },
        "categories": sorted(set(categories.values()) | set(_init_categories(config.init_from))),
        "training_time_s": round(_elapsed_before(log_path) + _init_time(config.init_from), 1),
        "validation": metrics,
        "voxel_size": config.voxel_size,
    }
    if config.init_from is not None:
        card["initialised_from"] = _init_card(config.init_from)
        card["carried_from_init"] = _carry_companions(config.init_from, config.out)
    return export_model(config.out, model, card)


# What serving reads beside the features' weights; a run started from shipped weights carries
# them, so that its folder serves as ``--model-dir`` at once.
COMPANIONS = (ORIENTATION_DIR, CALIBRATION_DIR, CATEGORIES_DIR)


def _carry_companions(init_from: Path, out: Path) -> list[str]:
    """Copy the orientation networks and the calibrator of ``init_from``, and those of its
    categories, into ``out`` (where it has none of its own); the names of those carried. The
    orientation networks read occupancy, not features, so they serve as they are; the
    calibrator was fitted on the old features' scores and stays an estimate until ``catalign
    calibrate`` runs on the new ones."""
    carried = []
    for name in COMPANIONS:
        if (init_from / name).is_dir() and not (out / name).exists():
            shutil.copytree(init_from / name, out / name)
            carried.append(name)
    return carried


def _resume(config: TrainConfig, model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> int:
    state = load_state(config.out)
    if state is None:
        return 0
    # A setting added after the run was saved counts at its default.
    saved = _plain(TrainConfig(**state["train_config"]))
    mine = _plain(config)
    differs = {k for k in mine if k not in ("out", "threads") and saved.get(k) != mine[k]}
    if differs:
        raise ConfigError(
            f"{config.out} holds a run with other settings ({', '.join(sorted(differs))}); "
            "use another --out or the same settings to resume"
        )
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    log.info("resuming %s at step %d", config.out, state["step"])
    return int(state["step"])


def _initial_weights(run: Path) -> dict[str, torch.Tensor]:
    """Weights of another run: its exported model, or else its latest training state."""
    state = load_state(run)
    if state is not None:
        return state["model"]
    from safetensors.torch import load_file

    weights = run / WEIGHTS_FILE
    if not weights.is_file():
        raise ConfigError(f"--init-from {run}: no {STATE_FILE} or {WEIGHTS_FILE} there")
    return load_file(str(weights))


def _init_card(run: Path) -> dict[str, Any]:
    """The model card of the run this one started from (its training counts in the total)."""
    path = run / CARD_FILE
    return json.loads(path.read_text()) if path.is_file() else {"run": str(run)}


def _init_categories(run: Path | None) -> list[str]:
    """The categories the starting weights had learnt (chairs for a card that names none)."""
    if run is None:
        return []
    card = _init_card(run)
    return list(card.get("categories", ["chair"] if "training" in card else []))


def _init_time(run: Path | None) -> float:
    return float(_init_card(run).get("training_time_s", 0.0)) if run is not None else 0.0


def _plain(config: TrainConfig) -> dict[str, Any]:
    return json.loads(config.model_dump_json())


def _append_csv(path: Path, row: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    new = not path.is_file()
    with open(path, "a", newline="") as handle:
        writer = csv.writer(handle)
        if new:
            writer.writerow(LOG_COLUMNS)
        writer.writerow([row.get(k, "") for k in LOG_COLUMNS])


def _truncate_log(path: Path, step: int) -> None:
    """Drop log rows after ``step``: a resumed run repeats the steps its checkpoint missed."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines()
    kept = [lines[0]] + [line for line in lines[1:] if int(line.split(",")[0]) <= step]
    path.write_text("\n".join(kept) + "\n")


def _elapsed_before(path: Path) -> float:
    """Training seconds already spent, read from the last line of the CSV log."""
    if not path.is_file():
        return 0.0
    lines = path.read_text().strip().splitlines()
    if len(lines) < 2:
        return 0.0
    return float(lines[-1].split(",")[LOG_COLUMNS.index("elapsed_s")])
