"""Typed results of the service's answers, parsed from JSON once at the edge.

Callers should get a numpy pose and attribute access they can rely on, not dictionaries whose
keys drift; parsing lives next to the types so a contract change touches one module. Unknown
extra keys are ignored (a newer server stays compatible), missing or mistyped ones raise
:class:`DecodingError`, since a pose built from a half-understood answer would move a robot arm to
the wrong place.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ._exceptions import DecodingError
from ._plot import plot_alignment

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ._points import PointsLike


@dataclass(frozen=True, slots=True)
class Candidate:
    """One library model the server tried, with its score (higher is better)."""

    model_id: str
    score: float


@dataclass(frozen=True, slots=True)
class Symmetry:
    """The turns about a model's up under which it looks the same: a rectangular table turned
    half way round, a square one a quarter turn, a round one by any angle. A pose composed with
    any of these turns is as right as the pose itself.

    ``order`` is 1 for none, n >= 2 for every turn of 360/n degrees, 0 for any turn;
    ``yaws_deg`` lists the turns (0 first; empty for order 0).
    """

    order: int = 1
    yaws_deg: tuple[float, ...] = (0.0,)

    @property
    def continuous(self) -> bool:
        """Whether the model looks the same turned by any angle."""
        return self.order == 0

    def to_dict(self) -> dict[str, Any]:
        return {"order": self.order, "yaws_deg": list(self.yaws_deg)}

    @classmethod
    def from_json(cls, data: Any) -> Symmetry:
        body = _mapping(data, "symmetry")
        return cls(
            order=_int(body, "order"),
            yaws_deg=tuple(float(v) for v in _list(body, "yaws_deg")),
        )


class _Posed:
    """The rotation and translation of a ``pose`` (4x4, model -> observation) with a
    ``scale``."""

    pose: np.ndarray
    scale: float

    @property
    def rotation(self) -> np.ndarray:
        """The 3x3 rotation, with any estimated scale divided out."""
        return self.pose[:3, :3] / self.scale

    @property
    def translation(self) -> np.ndarray:
        """The (3,) translation of the model origin in the observation frame."""
        return self.pose[:3, 3].copy()


@dataclass(frozen=True, eq=False)
class Alternative(_Posed):
    """Another distinct answer the server found: another model, or the same one turned by more
    than 30 degrees (e.g. a nearly symmetric chair seen back to front).

    ``pose`` is a read-only 4x4 float64 model -> observation matrix, like
    :attr:`AlignResult.pose`; ``score`` is its verification score (as the candidates'),
    ``fitness`` its share of query points within the inlier distance and ``confidence`` the
    probability that it is the right answer instead (``None`` when the server has no
    calibrator).
    """

    model_id: str
    pose: np.ndarray = field(repr=False)
    scale: float
    score: float
    fitness: float
    confidence: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready data, the pose as nested lists (the wire format)."""
        return {
            "model_id": self.model_id,
            "pose": self.pose.tolist(),
            "scale": self.scale,
            "score": self.score,
            "fitness": self.fitness,
            "confidence": self.confidence,
        }

    @classmethod
    def from_json(cls, data: Any) -> Alternative:
        """Parse one item of a register answer's ``alternatives``."""
        body = _mapping(data, "alternative")
        return cls(
            model_id=_str(body, "model_id"),
            pose=_pose(body.get("pose")),
            scale=_float(body, "scale") if "scale" in body else 1.0,
            score=_float(body, "score"),
            fitness=_float(body, "fitness"),
            confidence=_optional_float(body, "confidence"),
        )


@dataclass(frozen=True, eq=False)
class AlignResult(_Posed):
    """The best library model for a query cloud, its pose and inlier statistics.

    ``pose`` is a read-only 4x4 float64 matrix mapping model coordinates (of the library entry's
    source file) into the observation: ``x_obs = pose[:3, :3] @ x_model + pose[:3, 3]``. With
    ``estimate_scale`` the upper-left block is ``scale * rotation``. ``points_set_aside``
    counts query points the server dropped before registering (far outliers, the floor, small
    detached clusters). ``up`` is the up direction the pose was searched under: the request's,
    or the server's estimate when ``up_estimated`` (``None`` for a free search).

    ``confidence`` is the probability that the pose is right (the right model within 10 degrees
    and 5 cm of the truth), calibrated by the server on views of training chairs; ``None`` when
    the server's weights have no calibrator. ``accepted`` is ``False`` only when the request
    gave ``min_confidence`` and the confidence is below it (or unknown); the pose is still
    there, and ``reason`` says why in a sentence. ``alternatives`` are up to 3 other distinct
    answers (:class:`Alternative`), best first. ``category`` is the answer's model's category
    and ``symmetry`` its :class:`Symmetry` (``None`` from servers that do not report them);
    ``category_confidence`` the share of the answers' confidence on that category (near 1 when
    no model of another category came close; ``None`` without a calibrator).

    Usage::

        result = client.align(points, min_confidence=0.8)
        if not result.accepted:
            print(result.reason)  # e.g. look from another side and try again
        model_in_camera = model_points @ result.pose[:3, :3].T + result.translation
    """

    model_id: str
    pose: np.ndarray = field(repr=False)
    scale: float
    fitness: float
    inlier_rmse: float
    num_inliers: int
    inlier_ratio: float
    candidates: list[Candidate]
    timings_ms: dict[str, float] = field(repr=False)
    request_id: str
    points_set_aside: int = 0
    up: tuple[float, float, float] | None = None
    up_estimated: bool = False
    confidence: float | None = None
    accepted: bool = True
    reason: str | None = None
    alternatives: list[Alternative] = field(default_factory=list)
    category: str | None = None
    symmetry: Symmetry | None = None
    category_confidence: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready data, the pose as nested lists (the wire format)."""
        return {
            "model_id": self.model_id,
            "category": self.category,
            "symmetry": None if self.symmetry is None else self.symmetry.to_dict(),
            "category_confidence": self.category_confidence,
            "pose": self.pose.tolist(),
            "scale": self.scale,
            "fitness": self.fitness,
            "inlier_rmse": self.inlier_rmse,
            "num_inliers": self.num_inliers,
            "inlier_ratio": self.inlier_ratio,
            "candidates": [{"model_id": c.model_id, "score": c.score} for c in self.candidates],
            "timings_ms": dict(self.timings_ms),
            "request_id": self.request_id,
            "points_set_aside": self.points_set_aside,
            "up": None if self.up is None else list(self.up),
            "up_estimated": self.up_estimated,
            "confidence": self.confidence,
            "accepted": self.accepted,
            "reason": self.reason,
            "alternatives": [a.to_dict() for a in self.alternatives],
        }

    def plot(
        self,
        observed: PointsLike,
        model_points: PointsLike,
        path: str | Path | None = None,
        *,
        title: str | None = None,
    ) -> Figure:
        """Draw the observation against the posed model in three orthographic views.

        The views are top, front and side around :attr:`up` when the answer has one (else
        x-y, x-z and y-z); ``model_points`` (in model coordinates, e.g. from
        :meth:`Client.model_points`) are moved by :attr:`pose` and drawn in another colour. The
        title names the model and the fitness. Returns the matplotlib ``Figure`` and writes a
        PNG to ``path`` when given. Needs matplotlib: ``pip install "catalign-client[plot]"``.

        Usage::

            result = client.align(points, up=(0, 0, 1))
            model = client.model_points(result.model_id)
            result.plot(points, model, "alignment.png")
        """
        return plot_alignment(self, observed, model_points, path, title=title)

    @classmethod
    def from_json(cls, data: Any, *, up: tuple[float, float, float] | None = None) -> AlignResult:
        """Parse the body of a ``POST /register`` answer; ``up`` is the request's, if any, for
        answers of servers that do not report the up they used."""
        body = _mapping(data, "register answer")
        pose = _pose(body.get("pose"))
        candidates = [
            Candidate(model_id=_str(item, "model_id"), score=_float(item, "score"))
            for item in _list(body, "candidates")
        ]
        timings = _mapping(body.get("timings_ms", {}), "timings_ms")
        return cls(
            model_id=_str(body, "model_id"),
            pose=pose,
            scale=_float(body, "scale") if "scale" in body else 1.0,
            fitness=_float(body, "fitness"),
            inlier_rmse=_float(body, "inlier_rmse"),
            num_inliers=_int(body, "num_inliers"),
            inlier_ratio=_float(body, "inlier_ratio"),
            candidates=candidates,
            timings_ms={str(k): _float(timings, k) for k in timings},
            request_id=str(body.get("request_id") or ""),
            points_set_aside=_int(body, "points_set_aside") if "points_set_aside" in body else 0,
            up=_vec3(body, "up") if body.get("up") is not None else up,
            up_estimated=bool(body.get("up_estimated", False)),
            confidence=_optional_float(body, "confidence"),
            accepted=_bool(body, "accepted") if "accepted" in body else True,
            reason=_optional_str(body, "reason"),
            alternatives=[
                Alternative.from_json(item)
                for item in (_list(body, "alternatives") if "alternatives" in body else [])
            ],
            category=_optional_str(body, "category"),
            symmetry=(
                None if body.get("symmetry") is None else Symmetry.from_json(body["symmetry"])
            ),
            category_confidence=_optional_float(body, "category_confidence"),
        )


@dataclass(frozen=True, slots=True)
class ModelInfo:
    """One CAD model of the server's library.

    Parameters:
        model_id: the library id (the file stem unless given at upload).
        source: the file the entry was built from.
        units: the length unit of the model's coordinates, e.g. ``"m"``.
        num_points: how many surface points the library keeps for it.
        bbox_min, bbox_max, size: its axis-aligned bounding box, in ``units``.
        category: the kind of object it is, e.g. ``"chair"`` or ``"table"``.
        symmetry: the turns about its up under which it looks the same.
    """

    model_id: str
    source: str
    units: str
    num_points: int
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    size: tuple[float, float, float]
    category: str = "chair"
    symmetry: Symmetry = Symmetry()

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready data, as the server sent it."""
        return {
            "model_id": self.model_id,
            "category": self.category,
            "symmetry": self.symmetry.to_dict(),
            "source": self.source,
            "units": self.units,
            "num_points": self.num_points,
            "bbox_min": list(self.bbox_min),
            "bbox_max": list(self.bbox_max),
            "size": list(self.size),
        }

    @classmethod
    def from_json(cls, data: Any) -> ModelInfo:
        """Parse one model object of ``GET /models`` or ``GET /models/{id}``."""
        body = _mapping(data, "model")
        return cls(
            model_id=_str(body, "model_id"),
            category=str(body.get("category") or "chair"),  # servers before categories: chairs
            source=str(body.get("source") or ""),
            units=str(body.get("units") or ""),
            num_points=_int(body, "num_points"),
            bbox_min=_vec3(body, "bbox_min"),
            bbox_max=_vec3(body, "bbox_max"),
            size=_vec3(body, "size"),
            symmetry=(  # servers before symmetries: none known
                Symmetry() if body.get("symmetry") is None else Symmetry.from_json(body["symmetry"])
            ),
        )


def parse_models(data: Any) -> tuple[list[ModelInfo], str | None]:
    """Parse one page of ``GET /models``: its models and the cursor of the next page (None on
    the last page, and from servers that answer in one page)."""
    body = _mapping(data, "models answer")
    models = [ModelInfo.from_json(item) for item in _list(body, "models")]
    return models, _optional_str(body, "next_cursor")


def parse_removed_count(data: Any) -> int:
    """The number of models left, from the body of ``DELETE /models/{id}``."""
    return _int(_mapping(data, "remove answer"), "count")


def _mapping(value: Any, what: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise DecodingError(f"expected a JSON object for {what}, got {type(value).__name__}")
    return value


def _get(body: Mapping[str, Any], key: str) -> Any:
    if key not in body:
        raise DecodingError(f"answer lacks {key!r}")
    return body[key]


def _str(body: Any, key: str) -> str:
    value = _get(_mapping(body, key), key)
    if not isinstance(value, str):
        raise DecodingError(f"{key!r} is not a string: {value!r}")
    return value


def _float(body: Any, key: str) -> float:
    value = _get(_mapping(body, key), key)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DecodingError(f"{key!r} is not a number: {value!r}")
    return float(value)


def _optional_float(body: Mapping[str, Any], key: str) -> float | None:
    """A number, or ``None`` when the answer has null or lacks the key (an older server)."""
    return None if body.get(key) is None else _float(body, key)


def _optional_str(body: Mapping[str, Any], key: str) -> str | None:
    return None if body.get(key) is None else _str(body, key)


def _bool(body: Mapping[str, Any], key: str) -> bool:
    value = _get(body, key)
    if not isinstance(value, bool):
        raise DecodingError(f"{key!r} is not true or false: {value!r}")
    return value


def _int(body: Any, key: str) -> int:
    value = _get(_mapping(body, key), key)
    if isinstance(value, bool) or not isinstance(value, int):
        raise DecodingError(f"{key!r} is not an integer: {value!r}")
    return value


def _list(body: Mapping[str, Any], key: str) -> list[Any]:
    value = _get(body, key)
    if not isinstance(value, list):
        raise DecodingError(f"{key!r} is not a list: {value!r}")
    return value


def _vec3(body: Mapping[str, Any], key: str) -> tuple[float, float, float]:
    value = _get(body, key)
    try:
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise DecodingError(f"{key!r} is not three numbers: {value!r}") from exc
    return (x, y, z)


def _pose(value: Any) -> np.ndarray:
    try:
        pose = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DecodingError(f"'pose' is not a 4x4 matrix of numbers: {value!r}") from exc
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise DecodingError(f"'pose' is not a finite 4x4 matrix: {value!r}")
    pose.setflags(write=False)
    return pose
