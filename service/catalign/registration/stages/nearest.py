"""Feature nearest neighbours: the putative matches between a query's features and a model's."""

from __future__ import annotations

import numpy as np


def _nearest_both_ways(query: np.ndarray, model: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each query's nearest model feature, and each model feature's nearest query feature.

    L2 by matrix products (far faster than KD-trees in 32 dimensions): the nearest ``m`` to
    ``q`` maximises ``q.m - |m|^2 / 2`` and the nearest ``q`` to ``m`` maximises
    ``q.m - |q|^2 / 2``, so no distance matrix is formed; for unit-norm features (FCGF's) the
    norm terms are constant and skipped, which measured 4x faster. Each direction gets its own
    product, laid out so that its arg-max runs along rows: a column-wise arg-max over the
    transpose of one shared product measured twice as slow.
    """
    if _unit_norm(query) and _unit_norm(model):
        return (query @ model.T).argmax(axis=1), (model @ query.T).argmax(axis=1)
    forward = (query @ model.T - 0.5 * (model * model).sum(axis=1)[None, :]).argmax(axis=1)
    backward = (model @ query.T - 0.5 * (query * query).sum(axis=1)[None, :]).argmax(axis=1)
    return forward, backward


def _unit_norm(features: np.ndarray) -> bool:
    return bool(np.all(np.abs(np.einsum("ij,ij->i", features, features) - 1.0) < 1e-4))


def mutual_nearest(query: np.ndarray, model: np.ndarray, min_mutual: int = 30) -> np.ndarray:
    """Index pairs (i, j) of feature nearest neighbours: the mutual ones when there are at
    least ``min_mutual``, else the nearest in both directions (each query's nearest model
    feature, and each model feature's nearest query), without repeats.

    Both directions, because one direction alone can collapse: a "hub" feature near the middle
    of the feature space can be every query's nearest, and pairs that all share one model
    point fix no pose."""
    forward, backward = _nearest_both_ways(query, model)
    is_mutual = backward[forward] == np.arange(len(query))
    if is_mutual.sum() >= min_mutual:
        mutual = np.flatnonzero(is_mutual)
        return np.stack([mutual, forward[mutual]], axis=1)
    # Each pair (i, j) as the one number i * len(model) + j: a 1-D unique sorts as fast as
    # an array can, and its order is the pairs' lexicographic order.
    codes = np.unique(
        np.concatenate(
            [
                np.arange(len(query)) * len(model) + forward,
                backward * len(model) + np.arange(len(model)),
            ]
        )
    )
    return np.stack(np.divmod(codes, len(model)), axis=1)


def mutual_count(query: np.ndarray, model: np.ndarray) -> int:
    """How many query features are their nearest model feature's nearest query feature."""
    forward, backward = _nearest_both_ways(query, model)
    return int((backward[forward] == np.arange(len(query))).sum())
