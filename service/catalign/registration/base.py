"""The registration interface every method implements (classic baseline and learned engine).

A :class:`Registrar` is prepared once with library shapes and then answers queries. Poses follow
ARCHITECTURE.md: ``x_observation = R @ x_model + t``, model coordinates as the library gave them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LibraryShape:
    """A library model as registration needs it: id and surface points in its own frame."""

    model_id: str
    points: np.ndarray


@dataclass(frozen=True)
class Candidate:
    """One library model tried for a query, with the score that ranked it."""

    model_id: str
    score: float


@dataclass(frozen=True)
class RegistrationResult:
    """The answer to one query.

    ``correspondences`` holds the putative matches (query points, model points) the pose was
    estimated from, when the method exposes them; evaluation turns them into MatchAcc.
    ``points_set_aside`` counts the caller's points dropped as far outliers before registering.
    """

    model_id: str
    pose: np.ndarray
    fitness: float
    inlier_rmse: float
    num_inliers: int
    inlier_ratio: float
    candidates: list[Candidate]
    timings_ms: dict[str, float]
    correspondences: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    scale: float = 1.0
    points_set_aside: int = 0


class Registrar(ABC):
    """A registration method: ``prepare`` once per library, then ``register`` per query."""

    name: str

    @abstractmethod
    def prepare(self, library: Sequence[LibraryShape]) -> None:
        """Precompute whatever the method needs per library model."""

    @abstractmethod
    def register(self, points: np.ndarray, *, seed: int = 0) -> RegistrationResult:
        """Find the best library model for ``points`` and its model-to-observation pose."""
