"""Metric-learning losses on matched voxel features.

* :func:`contrastive_loss`, the paper's: positives pulled within ``pos_margin`` (0.1), random
  negatives pushed beyond ``neg_margin`` (1.4), squared hinges on L2 feature distances;
* :func:`hardest_contrastive_loss`, FCGF's: each positive's *hardest* negative (the nearest in
  feature space among a random subset, excluding anything near it in the aligned frame) is
  pushed beyond ``neg_margin``.

Negatives are always taken farther than ``neg_radius`` from the anchor in the aligned frame, so
a voxel next to a true match is never punished for looking like it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

POS_MARGIN = 0.1
NEG_MARGIN = 1.4


@dataclass(frozen=True)
class LossTerms:
    loss: Tensor
    pos_distance: float
    neg_distance: float


def _positive_distances(fa: Tensor, fb: Tensor, positives: Tensor) -> Tensor:
    return (fa[positives[:, 0]] - fb[positives[:, 1]]).norm(dim=1)


def contrastive_loss(
    fa: Tensor,
    fb: Tensor,
    positives: Tensor,
    aligned_a: Tensor,
    aligned_b: Tensor,
    neg_radius: float,
    generator: torch.Generator,
    pos_margin: float = POS_MARGIN,
    neg_margin: float = NEG_MARGIN,
    negatives_per_positive: int = 1,
) -> LossTerms:
    """The paper's contrastive loss with random negatives."""
    pos = _positive_distances(fa, fb, positives)
    count = len(positives) * negatives_per_positive
    i = positives[:, 0].repeat(negatives_per_positive)
    j = torch.randint(len(fb), (count,), generator=generator)
    far = (aligned_a[i] - aligned_b[j]).norm(dim=1) > neg_radius
    neg = (fa[i[far]] - fb[j[far]]).norm(dim=1)
    return _hinges(pos, neg, pos_margin, neg_margin)


def hardest_contrastive_loss(
    fa: Tensor,
    fb: Tensor,
    positives: Tensor,
    aligned_a: Tensor,
    aligned_b: Tensor,
    neg_radius: float,
    generator: torch.Generator,
    pos_margin: float = POS_MARGIN,
    neg_margin: float = NEG_MARGIN,
    candidates: int = 512,
) -> LossTerms:
    """FCGF's hardest-contrastive loss, symmetric in the two clouds."""
    pos = _positive_distances(fa, fb, positives)
    hardest = []
    for anchor_f, anchor_x, other_f, other_x, index in (
        (fa, aligned_a, fb, aligned_b, positives[:, 0]),
        (fb, aligned_b, fa, aligned_a, positives[:, 1]),
    ):
        pool = torch.randperm(len(other_f), generator=generator)[:candidates]
        feature_distance = torch.cdist(anchor_f[index], other_f[pool])
        too_close = torch.cdist(anchor_x[index], other_x[pool]) < neg_radius
        feature_distance = feature_distance.masked_fill(too_close, float("inf"))
        nearest = feature_distance.min(dim=1).values
        hardest.append(nearest[torch.isfinite(nearest)])
    neg = torch.cat(hardest)
    return _hinges(pos, neg, pos_margin, neg_margin)


def _hinges(pos: Tensor, neg: Tensor, pos_margin: float, neg_margin: float) -> LossTerms:
    """Squared hinges: positives beyond ``pos_margin``, negatives within ``neg_margin``."""
    loss = torch.relu(pos - pos_margin).pow(2).mean() + _mean(torch.relu(neg_margin - neg).pow(2))
    return LossTerms(loss, _scalar(pos), _scalar(neg))


def _mean(values: Tensor) -> Tensor:
    return values.mean() if len(values) else values.sum()


def _scalar(values: Tensor) -> float:
    """Mean of a logged distance, detached; NaN when there is none."""
    return float(values.detach().mean()) if len(values) else float("nan")
