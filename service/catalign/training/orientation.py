"""Training the orientation proposal networks (:mod:`catalign.features.orientation`) on CPU.

The data are views the evaluation could have made, of training shapes only: every shape is
rendered ``views_per_shape`` times by a random camera, the chair upright (a share of them with
a ring of floor kept) or in any rotation, with sensor noise (a ``fused_share`` of them by 2 to
4 cameras at once, as a scan reconstructed from a moving sensor sees a chair). Views are
rendered once and cached; each step then draws fresh variations of them, so a few thousand
views go a long way:

* for the **up** network, a random rotation of the whole view (label: the chair's up turned
  with it) and a random number of points (a sparse sensor, a decimated scan); with
  ``up_frame`` ``"principal"``, the view then turned onto one of its principal frames, drawn
  at random, and the label with it;
* for the **heading** network, the view levelled by its true up tilted by up to
  ``tilt_deg`` (an imperfect up proposal, an imprecise IMU) and turned by a random yaw (label:
  the yaw of the levelled chair, and every yaw equivalent under the shape's symmetry about its
  up: a rectangular table is as right turned half way round, a round one at any yaw).

Labels are soft (a Gaussian of ``label_sigma_deg`` over the angle to the truth), and the loss is
the cross-entropy against them. At the end, accuracy is measured on views of the validation
shapes at a seed of their own, and written into the card beside the weights. A run trains for
one category of the shared shapes (chairs, with procedural chairs added, or tables); the
networks of another category than the general one ship in ``model_store/categories/<name>/``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from catalign.data.camera import random_camera
from catalign.data.reconstruction import reconstruct
from catalign.data.shapes import ProceduralChairs, Shape
from catalign.data.views import Floor, random_object_pose, render_view
from catalign.errors import ConfigError
from catalign.features.orientation import (
    CARD_FILE,
    HEADING_ANGLES,
    UP_DIRECTIONS,
    WEIGHTS_FILE,
    OrientationModel,
    OrientationProposer,
    load_orientation,
    occupancy_grids,
    principal_frames,
)
from catalign.frames import MODEL_UP
from catalign.geometry.levelling import leveller, yaw_of, yaw_rotations
from catalign.geometry.se3 import axis_angle, random_rotation
from catalign.geometry.symmetry import find_yaw_symmetry
from catalign.training.checkpoint import export_weights
from catalign.training.config import OrientationConfig
from catalign.training.loop import ShapeSource

# Held-out views are rendered at their own seed, never one the evaluation uses (0, 1).
HELD_OUT_SEED = 1_000


@dataclass(frozen=True)
class ViewSet:
    """Cached views: points (V,P,3) float32 in the world frame (the first ``counts[v]`` rows of
    view ``v`` are distinct points, the rest repeat them), each shape's model -> world rotation
    (V,3,3) and the order of its symmetry about its up (V,: 1 none, n a turn of 360/n degrees,
    0 any yaw; :class:`~catalign.geometry.symmetry.YawSymmetry`)."""

    points: np.ndarray
    counts: np.ndarray
    rotations: np.ndarray
    orders: np.ndarray

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(
            path,
            points=self.points,
            counts=self.counts,
            rotations=self.rotations,
            orders=self.orders,
        )

    @classmethod
    def load(cls, path: Path) -> ViewSet:
        """Views saved by :meth:`save`; a cache written before views kept their symmetry is
        read as views of asymmetric shapes, as they were trained then."""
        with np.load(path) as data:
            orders = data["orders"] if "orders" in data else np.ones(len(data["counts"]), int)
            return cls(data["points"], data["counts"], data["rotations"], orders)


def render_views(
    shapes: list[Shape],
    views_per_shape: int,
    *,
    seed: int,
    view_points: int,
    so3_share: float,
    floor_share: float,
    fused_share: float = 0.0,
    progress: bool = True,
) -> ViewSet:
    """``views_per_shape`` noisy partial views of each metric shape, as the evaluation makes
    them (an upright share, some with floor, the rest in any rotation); a ``fused_share`` of
    them are reconstructions (:func:`~catalign.data.reconstruction.reconstruct`: fused from a
    camera trajectory, cut out loosely), as a mapping robot sends them (a ScanNet chair is seen
    from most sides, a single depth image from one)."""
    points, counts, rotations, orders = [], [], [], []
    symmetries = [find_yaw_symmetry(shape.points).order for shape in shapes]
    jobs = [(s, v) for s in range(len(shapes)) for v in range(views_per_shape)]
    for s, v in tqdm(jobs, desc="render views", unit="view", disable=not progress):
        shape = shapes[s]
        rng = np.random.default_rng([seed, s, v])
        mode = "so3" if rng.random() < so3_share else "upright"
        pose = random_object_pose(rng, mode, height=shape.height / 2)
        floor = Floor() if mode == "upright" and rng.random() < floor_share else None
        if fused_share and rng.random() < fused_share:
            seen = reconstruct(shape, pose, rng).points
        else:
            seen = render_view(shape, pose, random_camera(pose[:3, 3], rng), rng, floor=floor)
        if len(seen) < 16:
            continue
        order = rng.permutation(len(seen))[:view_points]
        padded = np.resize(order, view_points)  # repeats the distinct points when too few
        points.append(seen[padded].astype(np.float32))
        counts.append(len(order))
        rotations.append(pose[:3, :3])
        orders.append(symmetries[s])
    return ViewSet(np.stack(points), np.asarray(counts), np.stack(rotations), np.asarray(orders))


def soft_labels(truth: np.ndarray, bins: np.ndarray, sigma_deg: float) -> np.ndarray:
    """(B,K) targets: a Gaussian of the angle between each true unit vector (B,D) and each
    bin's (K,D), normalised to sum to one."""
    angles = np.degrees(np.arccos(np.clip(truth @ bins.T, -1.0, 1.0)))
    weights = np.exp(-0.5 * (angles / sigma_deg) ** 2)
    return weights / weights.sum(axis=1, keepdims=True)


def heading_labels(headings: np.ndarray, orders: np.ndarray, sigma_deg: float) -> np.ndarray:
    """(B, HEADING_BINS) targets for true headings (B, radians) of shapes whose symmetry about
    their up has ``orders`` (B): the mean of the soft labels of every equivalent heading, and
    uniform for a shape that looks the same at any yaw (order 0)."""
    circle = np.stack([np.cos(HEADING_ANGLES), np.sin(HEADING_ANGLES)], axis=1)
    labels = np.full((len(headings), len(circle)), 1.0 / len(circle))
    for row, (heading, order) in enumerate(zip(headings, orders, strict=True)):
        if order == 0:
            continue
        turns = heading + 2 * np.pi * np.arange(order) / order
        vectors = np.stack([np.cos(turns), np.sin(turns)], axis=1)
        labels[row] = soft_labels(vectors, circle, sigma_deg).mean(axis=0)
    return labels


def tilted(direction: np.ndarray, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """``direction`` turned by up to ``max_deg`` degrees about a random perpendicular axis."""
    axis = np.cross(direction, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    return axis_angle(axis, np.radians(rng.uniform(0.0, max_deg))) @ direction


def samples(
    views: ViewSet, rows: np.ndarray, config: OrientationConfig, rng: np.random.Generator
) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray], np.ndarray]:
    """One batch: rotated views with their true ups, and levelled views with their headings."""
    rotated, ups, levelled, headings = [], [], [], []
    for row in rows:
        count = views.counts[row]
        keep = rng.integers(min(config.min_points, count), count + 1)
        points = views.points[row, rng.permutation(count)[:keep]].astype(np.float64)
        up = views.rotations[row] @ MODEL_UP
        turn = random_rotation(rng)
        if config.up_frame == "principal":
            turn = principal_frames(points @ turn.T)[rng.integers(4)].T @ turn
        rotated.append(points @ turn.T)
        ups.append(turn @ up)
        turn = yaw_rotations(rng.uniform(0, 2 * np.pi))[0]
        level = turn @ leveller(tilted(up, config.tilt_deg, rng))
        levelled.append(points @ level.T)
        headings.append(yaw_of(level @ views.rotations[row]))
    return (
        rotated,
        soft_labels(np.stack(ups), UP_DIRECTIONS, config.label_sigma_deg),
        levelled,
        heading_labels(np.asarray(headings), views.orders[rows], config.label_sigma_deg),
    )


def soft_cross_entropy(logits: Tensor, targets: np.ndarray) -> Tensor:
    return -(torch.from_numpy(targets).float() * torch.log_softmax(logits, dim=1)).sum(1).mean()


def train_orientation(
    config: OrientationConfig,
    views: ViewSet,
    held_out: ViewSet | None = None,
    progress: bool = True,
    data: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train the networks ``config.networks`` names on ``views``; export the weights and a card
    (with the accuracy on ``held_out`` views, when given, and what ``data`` says of the
    training data) to ``config.out``."""
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    model = OrientationModel(width=config.width, up_frame=config.up_frame, up_width=config.up_width)
    trained = ("up", "heading") if config.networks == "both" else (config.networks,)
    if config.init_from is not None:
        started_from(model, load_orientation(config.init_from).model, trained)
    # Only the trained networks run, so the other gets no gradient and keeps its weights.
    parameters = [p for name in trained for p in model.get_submodule(name).parameters()]
    optimizer = torch.optim.AdamW(parameters, lr=config.learning_rate, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=config.learning_rate, total_steps=config.steps
    )
    started = time.perf_counter()
    model.eval()
    for name in trained:
        model.get_submodule(name).train()  # a kept network's batch norms keep their statistics
    bar = tqdm(range(config.steps), desc="train orientation", disable=not progress)
    for step in bar:
        rng = np.random.default_rng([config.seed, step])
        rows = rng.integers(0, len(views.counts), config.batch_size)
        rotated, up_targets, levelled, heading_targets = samples(views, rows, config, rng)
        losses = {}
        if "up" in trained:
            losses["up"] = soft_cross_entropy(model.up(occupancy_grids(rotated)), up_targets)
        if "heading" in trained:
            heading_logits = model.heading(occupancy_grids(levelled))
            losses["heading"] = soft_cross_entropy(heading_logits, heading_targets)
        optimizer.zero_grad()
        sum(losses.values()).backward()
        optimizer.step()
        schedule.step()
        bar.set_postfix({name: f"{loss.item():.3f}" for name, loss in losses.items()})
    model.eval()
    seconds = time.perf_counter() - started
    accuracy = (
        None if held_out is None else proposal_accuracy(OrientationProposer(model, {}), held_out)
    )
    card = {
        "training": json.loads(config.model_dump_json()),
        "command": config.command(),
        "training_data": (data or {}) | {"views": len(views.counts)},
        "training_time_s": round(seconds, 1),
        "held_out_accuracy": accuracy,
    }
    return export_orientation(config.out, model, card)


def started_from(
    model: OrientationModel, start: OrientationModel, trained: tuple[str, ...]
) -> None:
    """``model``'s networks given ``start``'s weights where they have the same shape; a trained
    network of another shape (a wider up network) starts afresh, a kept one cannot."""
    for name in ("up", "heading"):
        ours, theirs = model.get_submodule(name), start.get_submodule(name)
        if ours.config == theirs.config:
            ours.load_state_dict(theirs.state_dict())
        elif name not in trained:
            raise ConfigError(
                f"the {name} network is kept from init_from, but its shape there "
                f"({theirs.config}) is not this run's ({ours.config})"
            )


def proposal_accuracy(proposer: OrientationProposer, views: ViewSet) -> dict[str, float]:
    """Shares of ``views`` (as they are: no augmentation) whose true up is within 15 degrees of
    the top-1 and of any of the top-3 up proposals, and whose true heading, the view levelled by
    its true up, is within 22.5 degrees of the top-1 and of either of the top-2 headings (of the
    nearest heading equivalent under the shape's symmetry; any heading of a shape symmetric at
    any yaw)."""
    up_hits = np.zeros((len(views.counts), 2), dtype=bool)
    heading_hits = np.zeros_like(up_hits)
    for row in range(len(views.counts)):
        points = views.points[row, : views.counts[row]].astype(np.float64)
        up = views.rotations[row] @ MODEL_UP
        ups = [p.value for p in proposer.ups(points, 3)]
        within = [np.degrees(np.arccos(np.clip(u @ up, -1, 1))) <= 15.0 for u in ups]
        up_hits[row] = [within[0], any(within)]
        level = leveller(up)
        truth = yaw_of(level @ views.rotations[row])
        order = int(views.orders[row])
        headings = [p.value for p in proposer.headings([points @ level.T], 2)[0]]
        near = [_heading_off(h, truth, order) <= np.radians(22.5) for h in headings]
        heading_hits[row] = [near[0], any(near)]
    shares = np.concatenate([up_hits.mean(axis=0), heading_hits.mean(axis=0)])
    names = ("up_top1", "up_top3", "heading_top1", "heading_top2")
    return {name: round(float(share), 4) for name, share in zip(names, shares, strict=True)}


def _heading_off(heading: float, truth: float, order: int) -> float:
    """Radians from ``heading`` to the nearest heading equivalent to ``truth`` under a symmetry
    of ``order`` (0: any yaw, so none)."""
    if order == 0:
        return 0.0
    step = 2 * np.pi / order
    return float(abs((heading - truth + step / 2) % step - step / 2))


def export_orientation(directory: Path, model: OrientationModel, card: dict[str, Any]) -> dict:
    """Write the weights and their card (with the weights' sha256) to ``directory``."""
    return export_weights(directory, model, card, WEIGHTS_FILE, CARD_FILE)


def run(config: OrientationConfig, shared: ShapeSource, progress: bool = True) -> dict[str, Any]:
    """The whole command: render (or reuse) the training views of the ``shared`` training
    shapes (the shared chairs or tables, or a user's CAD folder), with ``config.procedural``
    procedural chairs beside chairs, and held-out views of the validation shapes at a seed of
    their own; train; export."""
    cache = config.out / "views.npz"
    train_ids, val_ids = shared.ids("train"), shared.ids("val")
    category = shared.category
    procedural = config.procedural if category == "chair" else 0
    if cache.is_file():
        views = ViewSet.load(cache)
    else:
        shapes = [shared.metric(i) for i in train_ids]
        shapes += list(ProceduralChairs(procedural))
        views = render_views(
            shapes,
            config.views_per_shape,
            seed=config.seed,
            fused_share=config.fused_share,
            **_rendering(config),
        )
        views.save(cache)
    held_out_shapes = [shared.metric(i) for i in val_ids]
    held_out = render_views(held_out_shapes, 4, seed=HELD_OUT_SEED, **_rendering(config))
    counted = f"shared_train_{category}s" if config.data is None else f"train_{category}s"
    data = {
        "category": category,
        counted: len(train_ids),
        "procedural_chairs": procedural,
        "symmetric_train_views": int((views.orders != 1).sum()),
        "held_out": f"4 views of each of {len(val_ids)} validation {category}s, "
        f"seed {HELD_OUT_SEED}",
    }
    return train_orientation(config, views, held_out, progress, data)


def _rendering(config: OrientationConfig) -> dict[str, Any]:
    return {
        "view_points": config.view_points,
        "so3_share": config.so3_share,
        "floor_share": config.floor_share,
    }
