"""Validation during training: how often feature nearest neighbours are true correspondences.

For each validation pair, every voxel of cloud A that has a true match gets its nearest
neighbour in B in feature space; it is an inlier when that neighbour lies within the pair's
positive radius in the aligned frame. MatchAcc is the mean inlier ratio; feature-match recall
(FMR, as in FCGF) is the share of pairs whose inlier ratio exceeds 5%.
"""

from __future__ import annotations

import numpy as np
import torch

from catalign.features.resunet import ResUNet2
from catalign.training.batches import pair_features
from catalign.training.pairs import PairSample

FMR_INLIER_THRESHOLD = 0.05


def inlier_ratio(fa: np.ndarray, fb: np.ndarray, sample: PairSample, tau: float) -> float:
    """Share of A's matchable voxels whose feature nearest neighbour in B is a true match."""
    anchors = np.unique(sample.positives[:, 0])
    if len(anchors) == 0:
        return 0.0
    nearest = torch.cdist(torch.from_numpy(fa[anchors]), torch.from_numpy(fb)).argmin(dim=1)
    gap = np.linalg.norm(sample.a.aligned[anchors] - sample.b.aligned[nearest.numpy()], axis=1)
    return float((gap < tau).mean())


def validate(model: ResUNet2, pairs: list[PairSample], taus: dict[str, float]) -> dict[str, float]:
    """MatchAcc and FMR per pair kind (``same``, ``cross``), in percent."""
    model.eval()
    ratios: dict[str, list[float]] = {}
    with torch.inference_mode():
        for sample in pairs:
            fa, fb = pair_features(model, [sample])[0]
            ratio = inlier_ratio(fa.numpy(), fb.numpy(), sample, taus[sample.kind])
            ratios.setdefault(sample.kind, []).append(ratio)
    model.train()
    metrics = {}
    for kind, values in sorted(ratios.items()):
        metrics[f"{kind}_match_acc"] = float(np.mean(values) * 100)
        metrics[f"{kind}_fmr"] = float(np.mean(np.array(values) > FMR_INLIER_THRESHOLD) * 100)
    return metrics
