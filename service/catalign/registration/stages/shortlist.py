"""Shortlisting: the library models worth registering the query against, best first.

Matching and RANSAC cost the same for every candidate, so the query is first compared with every
library entry through the cheap scores of :mod:`catalign.library.retrieval`: global-descriptor
similarity, a size check, and with ``up`` the query's height (a view usually shows a chair from
its feet to the top of its back). The query is scored at each heading it was described at and
keeps each model's best score, since only the right heading's features look like the models'.
The order matters even when every model is kept: the first few also choose the headings. With
the extractor's retrieval encoders, each heading's view is described by the view encoder, its
key points turned into the canonical frame at that heading, as the features were computed.
In a large library with an index (:mod:`catalign.library.shortlist_index`), only the index's
nearest neighbours of each heading's descriptor and the entries it does not hold are scored.
In a category of at least ``fit_from`` models, the best ``fit_candidates`` by those scores are
then re-ranked by how well the view lies on each
one's outline (:mod:`catalign.library.outline`), at the heading it scored best at: the descriptor
finds the few hundred models a view may show, the fit picks the few worth registering.
"""

from __future__ import annotations

import numpy as np

from catalign.features.retrieval import RetrievalHead
from catalign.library.loaded import Library
from catalign.library.outline import OUTLINE_TRUNCATION, fit_distances
from catalign.library.retrieval import global_descriptor, retrieval_scores
from catalign.registration.stages.describe import QueryView


def shortlist(
    library: Library,
    views: list[QueryView],
    k: int | None,
    turn: np.ndarray | None,
    rows: np.ndarray | None = None,
    retrieval: RetrievalHead | None = None,
    category: str | None = None,
    index_from: int | None = None,
    index_candidates: int | None = None,
    fit_from: int | None = None,
    fit_candidates: int | None = None,
    fit_weight: float = 0.0,
) -> list[str]:
    """The ids of the ``k`` (None: all) library models most like the query, best first (ties
    in library order), among ``rows`` (a mask over the library's ids: a category's; None:
    every model). ``views`` are the query at each heading; ``turn`` is the levelling turn when
    ``up`` is known (its second row is ``up`` in the observation frame), else None;
    ``retrieval`` the encoders that describe the views (None: their pooled features);
    ``category`` the one ``rows`` are of (None: every model). When at least ``index_from``
    models are searched and the library has an index, only the index's ``index_candidates``
    nearest entries to each heading's descriptor and the unindexed ones are scored (either
    None: every model is). When at least ``fit_from`` models are searched, the best
    ``fit_candidates`` then lose ``fit_weight`` per metre of their outline fit (either None:
    no fit)."""
    keypoints = views[0].keypoints
    size = np.ptp(keypoints, axis=0)
    height = None if turn is None else float(np.ptp(keypoints @ turn[1]))
    if retrieval is None:
        descriptors = np.stack([global_descriptor(v.features) for v in views])
        weight = 1.0
    else:
        turned = [(v.canonical_keypoints, v.features) for v in views]
        descriptors, weight = retrieval.view_descriptors(turned), retrieval.penalty_weight
    searched = len(library) if rows is None else int(np.count_nonzero(rows))
    index = library.index
    if (
        index is not None
        and k is not None
        and index_candidates is not None
        and index_from is not None
        and searched >= index_from
    ):
        candidates = index.candidates(descriptors, index_candidates, category)
        if rows is not None:
            candidates = candidates[rows[candidates]]
        scored = candidates
    else:
        candidates = np.arange(len(library)) if rows is None else np.flatnonzero(rows)
        scored = None if rows is None else candidates  # only the category's rows are scored
    per_view = retrieval_scores(library, descriptors, size, height, weight, scored)
    scores = per_view.max(axis=0)
    fitting = fit_from is not None and fit_candidates is not None and searched >= fit_from
    if fitting and len(candidates) > 0:
        fitted = _fitted(library, views, candidates, per_view, fit_candidates, fit_weight)
        candidates, scores = fitted
    count = len(candidates) if k is None else min(k, len(candidates))
    if 0 < count < len(candidates):  # only the best ``count`` (and any tied with the last)
        kth = -np.partition(-scores, count - 1)[count - 1]
        candidates, scores = candidates[scores >= kth], scores[scores >= kth]
    best = candidates[np.lexsort((candidates, -scores))]
    return [library.ids[i] for i in best[:count]]


def _fitted(
    library: Library,
    views: list[QueryView],
    candidates: np.ndarray,
    per_view: np.ndarray,
    count: int,
    weight: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``candidates`` scored again: the best ``count`` (by their best heading's score in
    ``per_view``) lose ``weight`` per metre of their outline fit at that heading, the others
    as much as the worst fit (the truncation), so that none of them passes a fitted one."""
    scores = per_view.max(axis=0)
    kept = np.lexsort((candidates, -scores))[:count]
    headings = per_view[:, kept].argmax(axis=0)
    fits = np.full(len(candidates), OUTLINE_TRUNCATION)
    for heading in np.unique(headings):
        at = kept[headings == heading]
        outlines = library.outlines(candidates[at])
        fits[at] = fit_distances(outlines, views[heading].canonical_keypoints)
    return candidates, scores - weight * fits
