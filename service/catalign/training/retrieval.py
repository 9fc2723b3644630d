"""Training the retrieval encoders (:mod:`catalign.features.retrieval`) on frozen features.

The FCGF network stays as it is; only the two small encoders on top of its features learn.
Their data is described once: every training model whole (its surface samples, as a library
entry describes them) and views of it, the evaluation protocol's (random pose, camera and
structured-light noise), each described after the turn that brings it to its true heading
give or take ``heading_error_deg``: the engine describes a view at proposed headings, which are
near the truth, not on it. The models are the shared training chairs and tables and
``procedural`` procedural chairs, which also give most of the negatives.

A step draws ``batch_size`` views of distinct models and scores each against those models and
``negatives`` others (InfoNCE at ``temperature``): a view must pick its own model out of them.
Random negatives are mostly easy; in a library of thousands the models that outrank a view's own
are the few most like it. So every ``mining_every`` steps every model is described once more,
and each view also meets ``hard_negatives`` drawn from the models its descriptor is nearest to
(hard-negative mining). Training may start from shipped encoders (``init_from``).
Views keep a random share of their points, so a narrow glimpse and a broad view both learn.
The held-out measurement uses the shared validation shapes, never trained on: each one's views
among every validation model and as many unseen procedural chairs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from catalign.data.shapes import Shape, procedural_shape
from catalign.errors import ConfigError
from catalign.evaluation.protocol import build_cases
from catalign.features.extractor import FeatureExtractor, features_fingerprint
from catalign.features.retrieval import (
    CARD_FILE,
    WEIGHTS_FILE,
    RetrievalHead,
    RetrievalModel,
    load_retrieval,
    packed,
)
from catalign.frames import MODEL_UP
from catalign.geometry.se3 import axis_angle
from catalign.training.checkpoint import export_weights
from catalign.training.config import RetrievalConfig
from catalign.training.loop import ShapeSource

HELD_OUT_SEED = 1000
HELD_OUT_VIEWS = 2
# Unseen procedural chairs among the held-out models: seeds far from any training run's.
HELD_OUT_PROCEDURAL_SEED = 50_000
MINING_POINTS = 512  # points of each model described for mining


@dataclass(frozen=True)
class Described:
    """Training clouds, each (canonical key points, features), and which model each shows."""

    clouds: list[tuple[np.ndarray, np.ndarray]]
    owners: np.ndarray


def describe_models(
    shapes: Sequence[Shape], extractor: FeatureExtractor, progress: bool
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every shape whole, described as a library entry is: its surface samples' key points
    and features in its canonical frame."""
    described = []
    for shape in tqdm(shapes, desc="describing models", unit="model", disable=not progress):
        found = extractor.describe(np.asarray(shape.points, dtype=np.float64))
        described.append((found.keypoints.astype(np.float32), found.features))
    return described


def describe_views(
    shapes: Sequence[Shape],
    views: int,
    extractor: FeatureExtractor,
    seed: int,
    heading_error_deg: float,
    progress: bool,
) -> Described:
    """``views`` of every shape, each described after the turn to its true heading plus a
    normal error of ``heading_error_deg``; key points stay in that (canonical) frame."""
    by_id = {s.shape_id: n for n, s in enumerate(shapes)}
    cases = build_cases({s.shape_id: s for s in shapes}, views, seed)
    rng = np.random.default_rng(seed)
    clouds, owners = [], []
    for case in tqdm(cases, desc="describing views", unit="view", disable=not progress):
        error = rng.normal(0.0, np.radians(heading_error_deg))
        turn = axis_angle(MODEL_UP, error) @ case.pose[:3, :3].T
        found = extractor.describe(case.points @ turn.T)
        if len(found.keypoints) == 0:
            continue
        clouds.append((found.keypoints.astype(np.float32), found.features))
        owners.append(by_id[case.shape_id])
    return Described(clouds, np.array(owners))


def train_encoders(
    config: RetrievalConfig,
    models: list[tuple[np.ndarray, np.ndarray]],
    views: Described,
    progress: bool,
    start: RetrievalModel | None = None,
) -> RetrievalModel:
    """The two encoders trained on ``views`` against ``models`` (module docstring), from
    ``start`` when given, else from scratch."""
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    if start is None:
        network = RetrievalModel(feature_dims=models[0][1].shape[1], dims=config.dims)
    else:
        network = start.train()
    optimiser = torch.optim.Adam(network.parameters(), lr=config.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, config.steps)
    seen = np.unique(views.owners)
    by_owner = {int(o): np.flatnonzero(views.owners == o) for o in seen}
    batch = min(config.batch_size, len(seen))
    bar = tqdm(range(config.steps), desc="training retrieval", unit="step", disable=not progress)
    bank = None
    for step in bar:
        if config.hard_negatives and step % config.mining_every == 0:
            bank = _described_models(network, models)
        positives = rng.choice(seen, batch, replace=False)
        chosen = [views.clouds[rng.choice(by_owner[int(o)])] for o in positives]
        view_in, view_mask = packed(chosen, config.view_points, rng)
        kept = torch.rand(view_mask.shape) < rng.uniform(config.min_view_share, 1.0)
        view_mask &= kept | (view_mask.cumsum(1) <= config.min_view_points)
        hard = np.zeros(0, int)
        if bank is not None:
            with torch.no_grad():
                nearest = network.view(view_in, view_mask) @ bank.T
            hard = _hardest(nearest, positives, config.hard_negatives, rng)
        others = np.setdiff1d(np.arange(len(models)), np.concatenate([positives, hard]))
        negatives = rng.choice(others, min(config.negatives, len(others)), replace=False)
        pool = [models[i] for i in np.concatenate([positives, hard, negatives])]
        model_in, model_mask = packed(pool, config.model_points, rng)
        logits = network.view(view_in, view_mask) @ network.model(model_in, model_mask).T
        loss = torch.nn.functional.cross_entropy(logits / config.temperature, torch.arange(batch))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        bar.set_postfix(loss=f"{loss.item():.3f}")
    return network.eval()


def _described_models(
    network: RetrievalModel, models: list[tuple[np.ndarray, np.ndarray]]
) -> torch.Tensor:
    """(M,D) every model's descriptor as the model encoder gives it now (for mining only:
    fewer points than training reads, to keep it cheap)."""
    network.eval()
    with torch.no_grad():
        described = [
            network.model(*packed(models[start : start + 64], MINING_POINTS))
            for start in range(0, len(models), 64)
        ]
    network.train()
    return torch.cat(described)


def _hardest(
    nearest: torch.Tensor, positives: np.ndarray, count: int, rng: np.random.Generator
) -> np.ndarray:
    """Each view's ``count`` hard negatives: drawn from the ``3 * count`` models other than the
    step's own that its descriptor is nearest to (a draw, so that one near-twin does not return
    every step); each model once."""
    nearest = nearest.clone()
    nearest[:, torch.from_numpy(positives)] = -torch.inf
    candidates = nearest.topk(min(3 * count, nearest.shape[1] - len(positives)), dim=1).indices
    drawn = [rng.choice(row, min(count, len(row)), replace=False) for row in candidates.numpy()]
    return np.unique(np.concatenate(drawn)).astype(int)


def held_out_recall(
    head: RetrievalHead,
    models: list[tuple[np.ndarray, np.ndarray]],
    views: Described,
    ranks: Sequence[int] = (1, 10),
) -> dict[str, float]:
    """The share of held-out views whose own model is among the best ``k`` of ``models`` by
    descriptor alone (no size or height penalty), for each ``k`` in ``ranks``."""
    library = np.stack([head.model_descriptor(k, f) for k, f in models])
    found = []
    for cloud, owner in zip(views.clouds, views.owners, strict=True):
        scores = library @ head.view_descriptors([cloud])[0]
        found.append(int((scores > scores[owner]).sum()))
    return {f"recall@{k}": float(np.mean(np.array(found) < k)) for k in ranks}


def run(
    config: RetrievalConfig,
    sources: Sequence[ShapeSource],
    extractor: FeatureExtractor,
    progress: bool = True,
) -> dict[str, Any]:
    """The whole command: describe, train, measure on held-out shapes, export; the card."""
    started = time.monotonic()
    parent = None if config.init_from is None else load_retrieval(config.init_from)
    if parent is not None and parent.card["extractor"] != features_fingerprint(
        extractor.fingerprint
    ):
        raise ConfigError(
            f"the encoders in {config.init_from} sit on the features of weights "
            f"{parent.card['extractor'][:16]}, not on these ({extractor.fingerprint[:16]}); "
            "train from scratch (no --init-from)"
        )
    train = [s.metric(i) for s in sources for i in s.ids("train")]
    train += [procedural_shape(config.procedural_first_seed + n) for n in range(config.procedural)]
    shared = len(train) - config.procedural
    rendered = [
        describe_views(group, count, extractor, config.seed, config.heading_error_deg, progress)
        for group, count in (
            (train[:shared], config.views_per_shape),
            (train[shared:], config.procedural_views),
        )
    ]
    views = Described(
        rendered[0].clouds + rendered[1].clouds,
        np.concatenate([rendered[0].owners, rendered[1].owners + shared]).astype(int),
    )
    models = describe_models(train, extractor, progress)
    network = train_encoders(
        config, models, views, progress, None if parent is None else parent.model
    )

    held = [s.metric(i) for s in sources for i in s.ids("val")]
    unseen = [procedural_shape(HELD_OUT_PROCEDURAL_SEED + n) for n in range(len(held))]
    held_views = describe_views(held, HELD_OUT_VIEWS, extractor, HELD_OUT_SEED, 0.0, progress)
    trained = RetrievalHead(network, {"penalty_weight": config.penalty_weight})
    recall = held_out_recall(
        trained, describe_models(held + unseen, extractor, progress), held_views
    )
    card: dict[str, Any] = {
        "kind": "retrieval",
        "command": config.command(),
        "extractor": features_fingerprint(extractor.fingerprint),
        "started_from": None if parent is None else parent.fingerprint,
        "penalty_weight": config.penalty_weight,
        "training": config.model_dump(mode="json"),
        "data": {
            "categories": [s.category for s in sources],
            "shared_train_shapes": shared,
            "procedural_chairs": config.procedural,
            "views": len(views.clouds),
        },
        "held_out": {
            "views": f"{HELD_OUT_VIEWS} of each of {len(held)} validation shapes, seed "
            f"{HELD_OUT_SEED}, at their true heading",
            "library": f"those shapes and {len(unseen)} unseen procedural chairs",
            **recall,
        },
        "minutes": round((time.monotonic() - started) / 60, 1),
    }
    return export_weights(config.out, network, card, WEIGHTS_FILE, CARD_FILE)
