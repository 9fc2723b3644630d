"""Pose transfer: every library model shares the canonical frame, so a pose found for one model
is a pose hypothesis for the others.

Feature matches of the observed chair's *own* CAD can fail where a near-twin's succeed (the
features were not trained on it, the view is small), and then the twin wins although the right
model, posed where the twin is, explains the view better. The search therefore carries its
``poses`` best verified poses over to each of its ``models`` best shortlisted candidates, with
the candidate's bounding-box centre (the category-level origin) put where the pose puts the
source model's; verification scores them like every other hypothesis, and ICP finishes those
that lead.
"""

from __future__ import annotations

import numpy as np

from catalign.geometry.se3 import make_pose
from catalign.library.index import Library
from catalign.registration.hypothesise import NO_MATCHES, Hypothesis
from catalign.registration.verify import Scored


def transferred(
    library: Library, ranked: list[Scored], candidates: list[str], *, poses: int, models: int
) -> list[Hypothesis]:
    """The ``poses`` best of ``ranked`` (best first) carried over to each of the first
    ``models`` of ``candidates`` other than their own model. A carried pose has no matches of
    its own."""
    carried = []
    for item in ranked[:poses]:
        source = item.hypothesis
        centre = library[source.model_id].centre
        for model_id in candidates[:models]:
            if model_id == source.model_id:
                continue
            shift = make_pose(np.eye(3), centre - library[model_id].centre)
            carried.append(Hypothesis(model_id, source.transform @ shift, NO_MATCHES, source.view))
    return carried
