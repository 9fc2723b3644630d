"""Orientation proposals: which way a partial view of a chair is up, and which way it faces.

The feature extractor only knows headings within half a bin of the canonical one, and the
gravity-aware search needs the chair's up. Both are guessed here, before any feature is
computed, by two small 3D convolutional networks on a coarse occupancy grid of the view:

* the **up** network sees the view in any rotation and scores :data:`UP_BINS` directions spread
  evenly over the sphere (a Fibonacci lattice, about 13 degrees apart). With ``up_frame``
  ``"principal"`` it sees the view turned onto its principal axes instead, once for each of the
  four ways to sign them (:func:`principal_frames`), and the four distributions, turned back,
  are averaged: the network then has a handful of poses of a view to learn, not all of SO(3);
* the **heading** network sees the view *levelled* (its up turned onto the models' +Y) and
  scores :data:`HEADING_BINS` headings about +Y.

Both are classifiers trained with soft labels (a kernel over the angle to the truth), so their
scores form a distribution whose peaks are the proposals: :func:`peaks` keeps the best distinct
ones, each refined to the probability-weighted mean direction around its peak. A grid of the
view's occupancy (not its point density) is what the networks see, so a dense sensor, a sparse
one and a decimated reconstruction look alike; the grid is centred on the view's centroid and
scaled to its extent, so a stool and a sofa fill it alike.

The weights and their card live in ``model_store/orientation/`` (:func:`load_orientation`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file
from torch import Tensor, nn

from catalign.features.weights import verified_card
from catalign.paths import CATEGORIES_DIR

GRID = 32
UP_BINS = 256
HEADING_BINS = 36
# A grid spans the view's centroid +- this many times its 95th-percentile radius.
GRID_REACH = 1.15
# Proposals closer than these to a better one are the same proposal.
UP_DISTINCT_DEG = 30.0
HEADING_DISTINCT_DEG = 45.0
ORIENTATION_DIR = "orientation"
WEIGHTS_FILE = "orientation.safetensors"
CARD_FILE = "orientation_card.json"


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    index = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * index / count)
    azimuth = np.pi * (1.0 + 5.0**0.5) * index
    return np.stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1
    )


UP_DIRECTIONS = fibonacci_sphere(UP_BINS)
HEADING_ANGLES = 2 * np.pi * np.arange(HEADING_BINS) / HEADING_BINS
# The proper rotations that flip two axes: a frame of principal axes is defined up to them.
AXIS_FLIPS = np.array([np.diag(s) for s in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))])
UP_FRAMES = ("view", "principal")


def principal_frames(points: np.ndarray) -> np.ndarray:
    """(4,3,3) rotations whose columns are the principal axes of ``points`` (widest spread
    first), one for each proper choice of their signs: ``points @ frame`` is the view in that
    frame, and ``frame @ d`` a direction ``d`` of that frame in the view's."""
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    axes = vectors[:, ::-1].copy()
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return axes @ AXIS_FLIPS


def occupancy_grids(clouds: list[np.ndarray], grid: int = GRID) -> Tensor:
    """(B,1,G,G,G) float occupancy of each cloud, centred on its centroid and scaled so that
    :data:`GRID_REACH` times its 95th-percentile radius fills the grid."""
    grids = np.zeros((len(clouds), grid**3), dtype=np.float32)
    for b, points in enumerate(clouds):
        centred = points - points.mean(axis=0)
        radius = max(float(np.percentile(np.linalg.norm(centred, axis=1), 95)), 1e-3)
        cells = np.floor((centred / (GRID_REACH * radius) + 1.0) * grid / 2).astype(np.int64)
        cells = cells[((cells >= 0) & (cells < grid)).all(axis=1)]
        grids[b, (cells[:, 0] * grid + cells[:, 1]) * grid + cells[:, 2]] = 1.0
    return torch.from_numpy(grids).view(len(clouds), 1, grid, grid, grid)


def _block(channels_in: int, channels_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv3d(channels_in, channels_out, 3, padding=1, bias=False),
        nn.BatchNorm3d(channels_out),
        nn.ReLU(inplace=True),
    )


class OrientationNet(nn.Module):
    """A small 3D CNN: a strided stem, three conv blocks with pooling, and a dense head.

    The head sees the flattened 4x4x4 map, not a global pool: where the parts are is the
    answer."""

    def __init__(self, outputs: int, width: int = 16, grid: int = GRID) -> None:
        super().__init__()
        self.config = {"outputs": outputs, "width": width, "grid": grid}
        w = width
        self.trunk = nn.Sequential(
            nn.Conv3d(1, w, 2, stride=2),  # 32 -> 16
            nn.ReLU(inplace=True),
            _block(w, w),
            nn.MaxPool3d(2),  # 16 -> 8
            _block(w, 2 * w),
            nn.MaxPool3d(2),  # 8 -> 4
            _block(2 * w, 4 * w),
        )
        cells = (grid // 8) ** 3
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(4 * w * cells, 256),
            nn.ReLU(inplace=True),
            nn.Dropout(0.2),
            nn.Linear(256, outputs),
        )

    def forward(self, grids: Tensor) -> Tensor:
        return self.head(self.trunk(grids))


class OrientationModel(nn.Module):
    """The up network and the heading network, shipped as one weights file. ``up_frame`` is
    the frame the up network sees a view in (module docstring); ``up_width``, when given, is
    the up network's width (finding up in any rotation asks more of it than a heading does)."""

    def __init__(
        self,
        width: int = 16,
        grid: int = GRID,
        up_frame: str = "view",
        up_width: int | None = None,
    ) -> None:
        super().__init__()
        if up_frame not in UP_FRAMES:
            raise ValueError(f"up_frame must be one of {UP_FRAMES}, not {up_frame!r}")
        self.config = {"width": width, "grid": grid, "up_frame": up_frame}
        if up_width is not None:
            self.config["up_width"] = up_width
        self.up_frame = up_frame
        self.up = OrientationNet(UP_BINS, width if up_width is None else up_width, grid)
        self.heading = OrientationNet(HEADING_BINS, width, grid)


@dataclass(frozen=True)
class Proposal:
    """A proposed direction (a unit 3-vector for up, an angle in radians for a heading) and
    the probability mass of its peak."""

    value: np.ndarray | float
    score: float


def peaks(
    probabilities: np.ndarray,
    directions: np.ndarray,
    count: int,
    distinct_deg: float,
) -> list[tuple[np.ndarray, float]]:
    """The ``count`` best distinct peaks of a distribution over unit ``directions`` (B,D):
    each the normalised probability-weighted mean of the directions within half
    ``distinct_deg`` of its best bin, with that mass as its score; bins within ``distinct_deg``
    of a chosen peak are not peaks again, and their mass counts for no later peak."""
    cosines = directions @ directions.T
    window = cosines >= np.cos(np.radians(distinct_deg / 2))
    suppressed = cosines >= np.cos(np.radians(distinct_deg))
    remaining = probabilities.astype(np.float64).copy()
    found = []
    while len(found) < count and remaining.max() > 0:
        best = int(np.argmax(remaining))
        mass = remaining[window[best]]  # what earlier peaks took is not this one's
        mean = mass @ directions[window[best]]
        found.append((mean / np.linalg.norm(mean), float(mass.sum())))
        remaining[suppressed[best]] = 0.0
    return found


class OrientationProposer:
    """Ranked proposals of a view's up and heading from the shipped networks."""

    def __init__(self, model: OrientationModel, card: dict[str, Any]) -> None:
        self.model = model.eval()
        self.card = card

    def ups(self, points: np.ndarray, count: int) -> list[Proposal]:
        """Up directions of the chair in ``points``' frame, best first."""
        if self.model.up_frame == "principal":
            frames = principal_frames(points)
            per_frame = self._probabilities(self.model.up, [points @ f for f in frames])
            # World bin k takes the probability of the frame's bin nearest to it.
            nearest = [np.argmax(UP_DIRECTIONS @ f @ UP_DIRECTIONS.T, axis=1) for f in frames]
            probabilities = np.mean([p[n] for p, n in zip(per_frame, nearest, strict=True)], 0)
            probabilities /= probabilities.sum()
        else:
            probabilities = self._probabilities(self.model.up, [points])[0]
        return [
            Proposal(direction, score)
            for direction, score in peaks(probabilities, UP_DIRECTIONS, count, UP_DISTINCT_DEG)
        ]

    def headings(self, levelled: list[np.ndarray], count: int) -> list[list[Proposal]]:
        """Headings (radians about +Y: the yaw that turns the model onto the view) of each
        levelled view, best first."""
        circle = np.stack([np.cos(HEADING_ANGLES), np.sin(HEADING_ANGLES)], axis=1)
        found = []
        for probabilities in self._probabilities(self.model.heading, levelled):
            tops = peaks(probabilities, circle, count, HEADING_DISTINCT_DEG)
            found.append([Proposal(float(np.arctan2(d[1], d[0])), s) for d, s in tops])
        return found

    @staticmethod
    def _probabilities(net: OrientationNet, clouds: list[np.ndarray]) -> np.ndarray:
        with torch.inference_mode():
            logits = net(occupancy_grids(clouds, net.config["grid"]))
        return torch.softmax(logits, dim=1).numpy()


def find_orientation(model_dir: Path) -> OrientationProposer | None:
    """The proposer shipped in ``model_dir``'s ``orientation/`` folder, None when it has none.
    Half of one (weights without their card, or the reverse) is refused, not ignored: without
    its proposer the engine answers views without ``up`` far worse, and would say nothing."""
    folder = model_dir / ORIENTATION_DIR
    shipped = (folder / WEIGHTS_FILE).is_file() or (folder / CARD_FILE).is_file()
    return load_orientation(folder) if shipped else None


def find_category_orientations(model_dir: Path) -> dict[str, OrientationProposer]:
    """The proposers trained for one category (``model_dir/categories/<name>/orientation/``),
    by category name; empty when the folder ships none."""
    found = {}
    for folder in sorted((model_dir / CATEGORIES_DIR).glob(f"*/{ORIENTATION_DIR}")):
        if (folder / WEIGHTS_FILE).is_file() or (folder / CARD_FILE).is_file():
            found[folder.parent.name] = load_orientation(folder)
    return found


def load_orientation(directory: Path) -> OrientationProposer:
    """The shipped proposer from ``directory`` (the weights and their card)."""
    card = verified_card(directory, WEIGHTS_FILE, CARD_FILE)
    model = OrientationModel(**card["architecture"])
    model.load_state_dict(load_file(str(directory / WEIGHTS_FILE)))
    return OrientationProposer(model, card)
