"""The registration interface every method implements (classic baseline and learned engine).

A :class:`Registrar` is prepared once with library shapes and then answers queries. Poses follow
the service's convention: ``x_observation = R @ x_model + t``, model coordinates as the library
gave them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from catalign.geometry.io import MeshData
from catalign.geometry.symmetry import YawSymmetry
from catalign.registration.decision.confidence import Evidence


@dataclass(frozen=True)
class LibraryShape:
    """A library model as registration needs it: id and surface points in its own frame, its
    mesh when it has one (a library samples a mesh itself, as ``catalign library build``
    samples a CAD file) and its category."""

    model_id: str
    points: np.ndarray
    mesh: MeshData | None = None
    category: str = "chair"


@dataclass(frozen=True)
class Candidate:
    """One library model tried for a query, with the score that ranked it."""

    model_id: str
    score: float


@dataclass(frozen=True)
class Orientation:
    """One way up a query was searched: ``up`` in the observation frame (None: a free search),
    whether the caller gave it, the ``headings`` (radians about ``up``, the yaw that turns the
    models' canonical frame onto the levelled query) it is described at, best first (with the
    engine's ``heading_mass``, only the confident ones unless the answer there is weak), and
    whether they were proposed (else they are evenly spaced), the belief in the up: the
    proposal's probability mass (1 for a given up or a floor under the cloud), the level
    of a floor found under the cloud: its height along ``up`` (None without one), every
    proposed heading with its probability mass, described or not (empty when none was), and
    whether the up is rough: a proposed up no plane confirmed, good to about ten degrees
    (:class:`~catalign.registration.prepare.orient.SearchedUp`)."""

    up: np.ndarray | None
    given: bool
    headings: tuple[float, ...]
    headings_proposed: bool = False
    belief: float = 1.0
    floor_level: float | None = None
    proposed_headings: tuple[tuple[float, float], ...] = ()
    up_rough: bool = False

    def heading_belief(self, yaw: float, window_deg: float) -> float:
        """The belief in a pose at ``yaw`` (radians about ``up``): the mass of the proposed
        heading within ``window_deg`` of it, else the mass no proposal holds (1 when no
        heading was proposed)."""
        if not self.proposed_headings:
            return 1.0
        headings, masses = np.array(self.proposed_headings).T
        near = np.abs(np.angle(np.exp(1j * (yaw - headings)))) <= np.radians(window_deg)
        return float(masses[near].max()) if near.any() else max(0.0, 1.0 - float(masses.sum()))


@dataclass(frozen=True)
class Alternative:
    """Another distinct answer to a query (another model, or the same one turned another
    way): its model -> observation pose, verification score, fitness, the probability that it
    is right (None without a calibrator), and the evidence that probability was read from."""

    model_id: str
    pose: np.ndarray
    score: float
    fitness: float
    confidence: float | None
    evidence: Evidence | None = field(default=None, repr=False)


@dataclass(frozen=True)
class RegistrationResult:
    """The answer to one query.

    ``correspondences`` holds the putative matches (query points, model points) the pose was
    estimated from, when the method exposes them; evaluation turns them into MatchAcc.
    ``points_set_aside`` counts the caller's points dropped before registering (far outliers,
    floor, detached clusters). ``orientations`` are the ways up the query was searched, best
    proposal first, and ``orientation`` the one the answer was found under (None for methods
    that do not orient the query). ``confidence`` is the probability that the answer is right
    (None for methods, or weights, without a calibrator), read from ``evidence``;
    ``alternatives`` are the other distinct answers, best first; ``category`` and ``symmetry``
    are the answer's model's (the pose composed with any of its symmetric turns is as right),
    ``category_confidence`` the share of the answers' confidence on that category.
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
    orientations: tuple[Orientation, ...] = field(default=(), repr=False)
    orientation: Orientation | None = None
    confidence: float | None = None
    evidence: Evidence | None = field(default=None, repr=False)
    alternatives: tuple[Alternative, ...] = ()
    category: str | None = None
    symmetry: YawSymmetry | None = None
    category_confidence: float | None = None

    @property
    def up(self) -> np.ndarray | None:
        """The up direction the answer was found under (None: a free search)."""
        return None if self.orientation is None else self.orientation.up

    @property
    def up_estimated(self) -> bool:
        """Whether that up was estimated from the cloud rather than given."""
        return self.up is not None and not self.orientation.given


class Registrar(ABC):
    """A registration method: ``prepare`` once per library, then ``register`` per query."""

    name: str

    @abstractmethod
    def prepare(self, library: Sequence[LibraryShape]) -> None:
        """Precompute whatever the method needs per library model."""

    @abstractmethod
    def register(
        self, points: np.ndarray, *, seed: int = 0, category: str | None = None
    ) -> RegistrationResult:
        """Find the best library model for ``points`` and its model-to-observation pose, of
        ``category`` when the query names one (as a detector's label would)."""
