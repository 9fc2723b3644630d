"""Run the network on a list of pair samples in one batched forward pass."""

from __future__ import annotations

import torch
from torch import Tensor

from catalign.features.resunet import ResUNet2
from catalign.features.sparse_tensor import sparse_collate
from catalign.training.pairs import PairSample


def pair_features(model: ResUNet2, samples: list[PairSample]) -> list[tuple[Tensor, Tensor]]:
    """Features ``(fa, fb)`` of every sample; all clouds go through the network together."""
    clouds = [cloud for s in samples for cloud in (s.a, s.b)]
    coords = [torch.from_numpy(c.coords) for c in clouds]
    ones = [torch.ones(len(c.coords), model.config["in_channels"]) for c in clouds]
    features = model(sparse_collate(coords, ones)).features
    parts = torch.split(features, [len(c.coords) for c in clouds])
    return [(parts[2 * k], parts[2 * k + 1]) for k in range(len(samples))]
