"""Shortlisting: which library models are worth registering a query against.

Registration is expensive per candidate, so a query is first compared with every entry through a
cheap global descriptor and a size check. The descriptor is the extractor's retrieval encoders'
when it has them (:mod:`catalign.features.retrieval`: a model's at build time, a view's at query
time, trained to land next to each other), else :func:`global_descriptor`, the same pooling of
features at build and query time. The size check: a partial view can be smaller than the
model it shows but not much larger, so a query whose largest extent exceeds a model's
bounding-box diagonal (the longest distance inside any box that holds the model, whatever the
query's orientation) is penalised.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from catalign.errors import DegenerateInputError, InvalidInputError

if TYPE_CHECKING:
    from catalign.features.extractor import FeatureExtractor
    from catalign.library.loaded import Library

SIZE_TOLERANCE = 0.15  # noise and stray points may stretch a view this much past the model
SIZE_PENALTY = 2.0  # score lost per unit of relative excess beyond the tolerance
# With gravity known the query's height is seen directly (feet to top of the back, in most
# views), and it is the sharpest cue a partial view gives: score lost per unit of relative
# height difference, halved when the view is the shorter one (its feet may be hidden).
HEIGHT_PENALTY = 4.0
_EPS = 1e-12


def global_descriptor(features: np.ndarray) -> np.ndarray:
    """One float32 vector per cloud: L2-normalised mean and max of its key-point features."""
    feats = np.asarray(features, dtype=np.float64)
    if feats.ndim != 2 or len(feats) == 0 or feats.shape[1] == 0:
        raise DegenerateInputError(
            f"a global descriptor needs an (M, D) array of features, got shape {feats.shape}"
        )
    return np.concatenate([_unit(feats.mean(axis=0)), _unit(feats.max(axis=0))]).astype(np.float32)


def model_descriptor(
    extractor: FeatureExtractor, keypoints: np.ndarray, features: np.ndarray
) -> np.ndarray:
    """A library model's descriptor (key points in its canonical frame): the retrieval
    encoders' when the extractor has them, else its pooled features."""
    if extractor.retrieval is None:
        return global_descriptor(features)
    return extractor.retrieval.model_descriptor(keypoints, features)


def retrieval_scores(
    library: Library,
    query_descriptor: np.ndarray,
    query_size: np.ndarray | None,
    query_height: float | None = None,
    penalty_weight: float = 1.0,
    entries: np.ndarray | None = None,
) -> np.ndarray:
    """Score of every entry, in ``library.ids`` order (or of the rows ``entries``, in their
    order): cosine similarity minus size penalties (times ``penalty_weight``: the descriptor's,
    see :class:`~catalign.features.retrieval.RetrievalHead`).

    ``query_descriptor`` is one descriptor (K,), or several (V,K) of the same query (seen at
    several headings): then the scores are (V,E), one matrix product for all. ``query_size`` is
    the query's bounding-box extents (``np.ptp(points, axis=0)``), in metres; ``None`` skips the
    size check. ``query_height`` is its extent along the up direction, when gravity is known:
    entries whose height (along +Y) differs lose :func:`height_penalty`.
    """
    query = np.asarray(query_descriptor, dtype=np.float32)
    if len(library) == 0:
        return np.zeros((*query.shape[:-1], 0))
    if query.shape[-1] != library.descriptors.shape[1]:
        raise InvalidInputError(
            f"the query descriptor has {query.shape[-1]} values but the library's have "
            f"{library.descriptors.shape[1]}; were they made by the same extractor?"
        )
    query = query / np.maximum(np.linalg.norm(query, axis=-1, keepdims=True), _EPS)
    every = entries is None
    descriptors = library.unit_descriptors if every else library.unit_descriptors[entries]
    model_sizes = library.sizes if every else library.sizes[entries]
    scores = (query @ descriptors.T).astype(np.float64)
    if query_size is not None:
        sizes = np.asarray(query_size, dtype=np.float64)
        scores -= penalty_weight * size_penalty(sizes, model_sizes)
    if query_height is not None:
        scores -= penalty_weight * height_penalty(query_height, model_sizes[:, 1])
    return scores


def size_penalty(query_size: np.ndarray, model_sizes: np.ndarray) -> np.ndarray:
    """Penalty (E,) for a query larger than each model: 0 up to the tolerance, then linear."""
    diagonals = np.linalg.norm(np.asarray(model_sizes, dtype=np.float64), axis=1)
    excess = float(np.max(query_size)) / np.maximum(diagonals, _EPS) - (1.0 + SIZE_TOLERANCE)
    return SIZE_PENALTY * np.clip(excess, 0.0, None)


def height_penalty(query_height: float, model_heights: np.ndarray) -> np.ndarray:
    """Penalty (E,) for the relative difference between the observed and each model's height."""
    heights = np.maximum(np.asarray(model_heights, dtype=np.float64), _EPS)
    relative = (query_height - heights) / heights
    return HEIGHT_PENALTY * np.where(relative > 0, relative, -0.5 * relative)


def shortlist(
    library: Library,
    query_descriptor: np.ndarray,
    query_size: np.ndarray | None,
    k: int | None,
) -> list[str]:
    """Ids of the ``k`` best entries, best first (ties by id); all of them when ``k`` is None
    or at least ``len(library)``."""
    if k is not None and k < 1:
        raise InvalidInputError(f"the shortlist size must be at least 1, got {k}")
    scores = retrieval_scores(library, query_descriptor, query_size)
    ids = library.ids
    order = sorted(range(len(ids)), key=lambda i: (-scores[i], ids[i]))
    if k is not None:
        order = order[:k]
    return [ids[i] for i in order]


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / max(float(np.linalg.norm(vector)), _EPS)
