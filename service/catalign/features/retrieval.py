"""Retrieval descriptors learned for partial views: which library models a view may show.

Mean- and max-pooled FCGF features describe a category, not an instance: the features are
trained so that corresponding parts of *different* chairs look alike, and a partial view pools
only the parts it sees. Two small encoders on top of the frozen features fix both: each point
is its feature and its position in the canonical frame (the view levelled and turned to a
heading, as the features were computed), a shared per-point MLP, max- and mean-pooled, then a
projection onto a unit vector. The **model** encoder describes a whole library model once, at
build time; the **view** encoder describes a partial view at each heading it is tried at. They
are trained together (:mod:`catalign.training.retrieval`) with a contrastive loss, so that a view
lands next to its own model and away from the others.

Positions are taken from an anchor a view and its model share: the centre of the cloud's
extent across the floor and its lowest point (a chair's feet or what the view shows of them),
so the proportions of a model, not only its parts, tell it apart.

The weights and their card live in ``model_store/retrieval/`` (:func:`find_retrieval`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file
from torch import Tensor, nn

from catalign.features.weights import verified_card
from catalign.geometry.levelling import floor_anchor

RETRIEVAL_DIR = "retrieval"
WEIGHTS_FILE = "retrieval.safetensors"
CARD_FILE = "retrieval_card.json"
# Points an encoder reads: a model's are subsampled to MODEL_POINTS (evenly through its key
# points, so a model always gets the same descriptor); a view keeps up to VIEW_POINTS.
MODEL_POINTS = 1024
VIEW_POINTS = 2048
POSITION_DIMS = 3


def anchored(keypoints: np.ndarray) -> np.ndarray:
    """Canonical-frame positions from the anchor a view shares with its model: the middle of
    the cloud's extent along x and z, its lowest point along the up (+Y)."""
    return (keypoints - floor_anchor(keypoints)).astype(np.float32)


class SetEncoder(nn.Module):
    """Points (position and feature) -> one unit vector: a shared per-point MLP, max- and
    mean-pooled over the points a mask keeps, then a projection."""

    def __init__(self, feature_dims: int = 32, width: int = 256, dims: int = 256) -> None:
        super().__init__()
        self.point = nn.Sequential(
            nn.Linear(POSITION_DIMS + feature_dims, 64),
            nn.ReLU(),
            nn.Linear(64, 128),
            nn.ReLU(),
            nn.Linear(128, width),
        )
        self.project = nn.Sequential(nn.Linear(2 * width, 256), nn.ReLU(), nn.Linear(256, dims))

    def forward(self, inputs: Tensor, mask: Tensor) -> Tensor:
        """``inputs`` (B,N,3+F) and ``mask`` (B,N) -> (B,dims) unit vectors."""
        hidden = self.point(inputs)
        kept = mask[..., None]
        pooled_max = hidden.masked_fill(~kept, torch.finfo(hidden.dtype).min).max(dim=1).values
        pooled_mean = (hidden * kept).sum(1) / kept.sum(1).clamp(min=1)
        return nn.functional.normalize(self.project(torch.cat([pooled_max, pooled_mean], 1)), dim=1)


class RetrievalModel(nn.Module):
    """The two encoders trained together: ``view`` for partial views, ``model`` for models."""

    def __init__(self, feature_dims: int = 32, width: int = 256, dims: int = 256) -> None:
        super().__init__()
        self.config = {"feature_dims": feature_dims, "width": width, "dims": dims}
        self.view = SetEncoder(feature_dims, width, dims)
        self.model = SetEncoder(feature_dims, width, dims)


def packed(
    clouds: Sequence[tuple[np.ndarray, np.ndarray]],
    points: int,
    rng: np.random.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Clouds of (canonical key points, features) as encoder inputs (B,N,3+F) and mask (B,N),
    ``N`` at most ``points``: larger clouds subsampled at random with ``rng``, else evenly."""
    width = POSITION_DIMS + clouds[0][1].shape[1]
    size = min(points, max(len(k) for k, _ in clouds))
    inputs = np.zeros((len(clouds), size, width), np.float32)
    mask = np.zeros((len(clouds), size), bool)
    for row, (keypoints, features) in enumerate(clouds):
        count = len(keypoints)
        if count <= size:
            chosen = np.arange(count)
        elif rng is None:
            chosen = np.linspace(0, count - 1, size).astype(int)
        else:
            chosen = rng.choice(count, size, replace=False)
        inputs[row, : len(chosen), :POSITION_DIMS] = anchored(np.asarray(keypoints)[chosen])
        inputs[row, : len(chosen), POSITION_DIMS:] = np.asarray(features)[chosen]
        mask[row, : len(chosen)] = True
    return torch.from_numpy(inputs), torch.from_numpy(mask)


class RetrievalHead:
    """The trained encoders with their card: a model's descriptor at build time, a view's at
    query time. ``penalty_weight`` is how much of the shortlist's size and height penalties
    (:mod:`catalign.library.retrieval`) is taken off a cosine of these descriptors, as chosen
    when the head was trained. ``fingerprint`` is its weights' sha256 (empty for encoders
    still in training, not yet exported)."""

    def __init__(self, model: RetrievalModel, card: dict[str, Any]) -> None:
        self.model = model.eval()
        self.card = card
        self.fingerprint = str(card.get("sha256", ""))
        self.penalty_weight = float(card.get("penalty_weight", 1.0))

    def model_descriptor(self, keypoints: np.ndarray, features: np.ndarray) -> np.ndarray:
        """(D,) float32: a library model (key points in its canonical frame)."""
        inputs, mask = packed([(keypoints, features)], MODEL_POINTS)
        with torch.inference_mode():
            return self.model.model(inputs, mask)[0].numpy().astype(np.float32)

    def view_descriptors(self, clouds: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """(V,D) float32: a view at each heading, as (key points turned into the canonical
        frame at that heading, the features described there)."""
        inputs, mask = packed(clouds, VIEW_POINTS)
        with torch.inference_mode():
            return self.model.view(inputs, mask).numpy().astype(np.float32)


def find_retrieval(model_dir: Path) -> RetrievalHead | None:
    """The head shipped in ``model_dir``'s ``retrieval/`` folder, None when it has none (the
    shortlist then pools the features instead); half of one is refused, not ignored."""
    folder = model_dir / RETRIEVAL_DIR
    if (folder / WEIGHTS_FILE).is_file() or (folder / CARD_FILE).is_file():
        return load_retrieval(folder)
    return None


def load_retrieval(directory: Path) -> RetrievalHead:
    """The head in ``directory`` (the weights and their card, checked against each other)."""
    card = verified_card(directory, WEIGHTS_FILE, CARD_FILE)
    model = RetrievalModel(**card["architecture"])
    model.load_state_dict(load_file(str(directory / WEIGHTS_FILE)))
    return RetrievalHead(model, card)
