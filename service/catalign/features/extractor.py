"""Feature extractors: what turns a cloud into key points with one descriptor each.

Registration and the library index only see this interface, so the learned FCGF model and the
classic FPFH descriptor are interchangeable. ``fingerprint`` names the exact extractor (the
weights' sha256 for the learned one, and its retrieval encoders' when it has them): a library
index built with one fingerprint is refused by another, because its stored features and
descriptors would not be comparable.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Protocol

import numpy as np
import torch

from catalign.features.orientation import (
    OrientationProposer,
    find_category_orientations,
    find_orientation,
)
from catalign.features.retrieval import RetrievalHead, find_retrieval
from catalign.paths import DEFAULT_MODEL_DIR


@dataclass(frozen=True)
class Described:
    """Key points (M,3) float64 and their descriptors (M,D) float32."""

    keypoints: np.ndarray
    features: np.ndarray


class FeatureExtractor(Protocol):
    """What registration and the library need of an extractor: its voxel size, its fingerprint,
    how many headings a query must be described at, the orientation proposals that choose them
    (None: every heading, and no up is proposed) and those of single categories, the retrieval
    encoders that shortlist models (None: pooled features do), the folder of
    its weights (None for a descriptor without any; the engine reads the answers' calibrator
    there), and the description itself."""

    voxel_size: float
    fingerprint: str
    headings: int
    orientation: OrientationProposer | None
    category_orientations: Mapping[str, OrientationProposer]
    retrieval: RetrievalHead | None
    model_dir: Path | None

    def describe(self, points: np.ndarray) -> Described: ...

    def describe_many(self, clouds: Sequence[np.ndarray]) -> list[Described]: ...


class LearnedExtractor:
    """FCGF descriptors of voxel centroids from a trained ResUNet (``model_store/`` layout).

    ``headings`` is how many headings a query must be tried at: 8 for a model trained on
    ``yaw-bin`` rotations (it only knows headings within 22.5 degrees), 4 for ``yaw-quarter``,
    else 1. ``orientation`` is the proposer in the folder's ``orientation/``, when it has one,
    and ``category_orientations`` those of its ``categories/<name>/orientation/`` (loaded once
    for every engine the process builds); ``model_dir`` the folder itself (its ``confidence/``
    calibrator is the engine's to read).
    """

    def __init__(self, model_dir: Path | None = None, threads: int | None = None) -> None:
        from catalign.features.weights import YAW_BINS, load_model

        self.model, self.card = load_model(model_dir or DEFAULT_MODEL_DIR)
        self.voxel_size = float(self.card["voxel_size"])
        self.retrieval = find_retrieval(model_dir or DEFAULT_MODEL_DIR)
        retrieval = None if self.retrieval is None else self.retrieval.fingerprint
        self.fingerprint = learned_fingerprint(str(self.card["sha256"]), retrieval)
        rotation = self.card.get("training", {}).get("rotation", "upright")
        self.headings = YAW_BINS.get(rotation, 1)
        self.orientation = find_orientation(model_dir or DEFAULT_MODEL_DIR)
        self.category_orientations = find_category_orientations(model_dir or DEFAULT_MODEL_DIR)
        self.model_dir = model_dir or DEFAULT_MODEL_DIR
        if threads is not None:
            torch.set_num_threads(threads)

    def describe(self, points: np.ndarray) -> Described:
        return self.describe_many([points])[0]

    def describe_many(self, clouds: Sequence[np.ndarray]) -> list[Described]:
        """Several clouds in one forward pass (each gets the features it would alone)."""
        from catalign.features.resunet import extract_features_batch

        with torch.inference_mode():
            described = extract_features_batch(self.model, clouds, self.voxel_size)
        return [Described(c.numpy().astype(np.float64), f.numpy()) for c, f in described]


def learned_fingerprint(weights_sha256: str, retrieval_sha256: str | None) -> str:
    """A learned extractor's fingerprint: its weights' sha256, then its retrieval encoders'
    (their descriptors are stored in the library too)."""
    if retrieval_sha256 is None:
        return weights_sha256
    return f"{weights_sha256}+retrieval-{retrieval_sha256[:16]}"


def features_fingerprint(fingerprint: str) -> str:
    """The part of an extractor's fingerprint that names its features (its weights' sha256),
    without its retrieval encoders: entries with the same one have comparable features."""
    return fingerprint.split("+retrieval-", 1)[0]


def fingerprint_in(model_dir: Path) -> str:
    """The fingerprint of the weights in ``model_dir`` from their cards alone (nothing loaded),
    for a check before a server starts; the cards' checksums are checked when it loads them."""
    from catalign.features.retrieval import CARD_FILE as RETRIEVAL_CARD
    from catalign.features.retrieval import RETRIEVAL_DIR
    from catalign.features.weights import CARD_FILE

    card = json.loads((model_dir / CARD_FILE).read_text())
    retrieval = model_dir / RETRIEVAL_DIR / RETRIEVAL_CARD
    encoders = json.loads(retrieval.read_text())["sha256"] if retrieval.is_file() else None
    return learned_fingerprint(str(card["sha256"]), encoders)


# The classic recipe's voxel (Open3D's global registration example at chair scale); the learned
# extractor's comes from its model card.
FPFH_VOXEL = 0.025


class FPFHExtractor:
    """Open3D's FPFH (33-D) on a voxel-down-sampled cloud: normals within 2 voxels, FPFH 5."""

    headings = 1  # rotation-invariant: one heading describes every heading
    orientation = None
    category_orientations: Mapping[str, OrientationProposer] = MappingProxyType({})
    retrieval = None
    model_dir = None

    def __init__(self, voxel_size: float = FPFH_VOXEL) -> None:
        self.voxel_size = voxel_size
        self.fingerprint = f"fpfh-v1-{voxel_size:g}"

    def describe(self, points: np.ndarray) -> Described:
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        down = np.asarray(cloud.voxel_down_sample(self.voxel_size).points)
        # Open3D's parallel down-sampling returns voxels in a varying order; sort them so that
        # the same cloud always gives the same key points in the same order (determinism)
        down = down[np.lexsort(down.T[::-1])]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(down))
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2 * self.voxel_size, max_nn=30)
        )
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.voxel_size, max_nn=100)
        )
        return Described(np.asarray(cloud.points).copy(), fpfh.data.T.astype(np.float32))

    def describe_many(self, clouds: Sequence[np.ndarray]) -> list[Described]:
        return [self.describe(points) for points in clouds]
