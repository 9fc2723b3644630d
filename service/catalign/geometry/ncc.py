"""Normalized Canonical Coordinates (NCC): centre the bounding box, scale to a unit diagonal.

Shapes of a category share a canonical orientation, so after this normalisation corresponding
parts of *different* instances land near each other; that is what makes cross-instance positive
pairs (and a category-level pose) meaningful.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NCCFrame:
    """The similarity that maps a shape's coordinates into NCC: ``(x - centre) / scale``."""

    centre: np.ndarray
    scale: float

    @classmethod
    def fit(cls, points: np.ndarray) -> NCCFrame:
        """Frame of a shape given in its canonical orientation (bounding-box centre, diagonal)."""
        lo, hi = points.min(axis=0), points.max(axis=0)
        diagonal = float(np.linalg.norm(hi - lo))
        if diagonal <= 0:
            raise ValueError("cannot normalise a shape whose points all coincide")
        return cls(centre=(lo + hi) / 2.0, scale=diagonal)

    def to_ncc(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale

    def from_ncc(self, points: np.ndarray) -> np.ndarray:
        return points * self.scale + self.centre

    def matrix(self) -> np.ndarray:
        """4x4 similarity matrix of :meth:`to_ncc`."""
        m = np.eye(4) / self.scale
        m[3, 3] = 1.0
        m[:3, 3] = -self.centre / self.scale
        return m


def to_ncc(points: np.ndarray) -> np.ndarray:
    """Shortcut: normalise ``points`` by their own bounding box."""
    return NCCFrame.fit(points).to_ncc(points)
