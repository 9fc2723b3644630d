"""Pydantic models of the HTTP contract: what requests may hold and what every answer holds.

One family per resource (registration, models, health, info, errors). The SDK in ``client/``
mirrors these fields, and ``openapi.yaml`` is generated from them, so a change here is a change
of the public contract. Converters from the engine's and the library's dataclasses live next to
the models they fill, so that routes only call them.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict, field_validator
from typing_extensions import TypeAliasType

from catalign.api.acceptance import acceptance
from catalign.geometry.se3 import scale_of
from catalign.library.sources import CATEGORY_PATTERN
from catalign.registration.config import EngineConfig

if TYPE_CHECKING:
    from catalign.geometry.symmetry import YawSymmetry
    from catalign.library.entry import LibraryEntry
    from catalign.library.loaded import Library
    from catalign.library.records import EntryRecord
    from catalign.registration.results import Alternative, RegistrationResult

MAX_SEED = 2**31 - 1
MAX_TOP_K = 10_000

# Plain JSON data, spelled out (pydantic's JsonValue renders as the untyped schema {}).
JsonData = TypeAliasType(
    "JsonData", "str | int | float | bool | list[JsonData] | dict[str, JsonData] | None"
)
StrictFloat = Annotated[float, Strict()]  # ints pass, strings and booleans do not
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Row4 = Annotated[list[float], Field(min_length=4, max_length=4)]
Row3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Pose4 = Annotated[list[Row4], Field(min_length=4, max_length=4)]

RIGHT_POSE = "the right model within 10 degrees and 5 cm of the truth"


class RegisterOptions(BaseModel):
    """Options of one registration (JSON body fields, or query parameters for other bodies).

    Strict: ``"seed": "7"`` or ``"estimate_scale": "yes"`` is refused, not guessed at (query
    parameters are typed by the route before they get here).
    """

    model_config = ConfigDict(extra="forbid")

    top_k: int | None = Field(
        default=None,
        strict=True,
        ge=1,
        le=MAX_TOP_K,
        description="Library models to register against, best retrieval scores first "
        "(default: the server's setting, normally every model).",
    )
    up: tuple[StrictFloat, StrictFloat, StrictFloat] | None = Field(
        default=None,
        description="The world's up direction when the chair stands upright (e.g. [0, 0, 1]); "
        "restricts poses to upright ones.",
    )
    estimate_scale: bool = Field(
        default=False,
        strict=True,
        description="Also estimate a uniform scale, between 0.5 and 2 times the model's size.",
    )
    seed: int = Field(
        default=0,
        strict=True,
        ge=0,
        le=MAX_SEED,
        description="RANSAC seed: same request, same answer.",
    )
    category: str | None = Field(
        default=None,
        strict=True,
        pattern=f"^{CATEGORY_PATTERN.pattern}$",
        description="Search only this category's models (e.g. table, as a detector labels the "
        "object); an unknown category is a 422 that lists the library's. Default: every model, "
        "and the answer says which category it chose.",
    )
    min_confidence: float | None = Field(
        default=None,
        strict=True,
        ge=0.0,
        le=1.0,
        allow_inf_nan=False,
        description="The confidence in [0, 1] the answer needs to be accepted. Below it, or when "
        "the server's weights have no calibrator, the answer is still a 200 with the pose, but "
        "with accepted false and a reason.",
    )

    @field_validator("up")
    @classmethod
    def _up_is_a_direction(
        cls, value: tuple[float, float, float] | None
    ) -> tuple[float, float, float] | None:
        if value is None:
            return None
        if not all(math.isfinite(v) for v in value) or math.hypot(*value) < 1e-9:
            raise ValueError("up must be a finite, non-zero direction like [0, 0, 1]")
        return value


class RegisterRequest(RegisterOptions):
    """``POST /register`` as JSON: the points and the options."""

    points: list[tuple[float, float, float]] = Field(
        description="The observed cloud, one [x, y, z] row per point (metres), at most the "
        "server's max_points (default 500,000).",
    )


class CandidatePublic(BaseModel):
    model_id: str
    score: float = Field(description="Alignment score: inlier share discounted by the RMSE.")


class SymmetryPublic(BaseModel):
    """The turns about a model's up under which it looks the same: a pose composed with any of
    them is as right as the pose itself."""

    order: int = Field(
        ge=0,
        description="1: none; n >= 2: every turn of 360/n degrees about the model's up (+Y) "
        "(2: a rectangular table, 4: a square one); 0: any turn (a round table).",
    )
    yaws_deg: list[float] = Field(
        description="The equivalent turns in degrees, 0 first; empty when any turn is (order 0)."
    )

    @classmethod
    def from_symmetry(cls, symmetry: YawSymmetry) -> SymmetryPublic:
        return cls(order=symmetry.order, yaws_deg=symmetry.yaws_deg)


class AlternativePublic(BaseModel):
    """Another distinct answer: another model, or the same one turned by over 30 degrees (and
    not by one of its symmetric turns)."""

    model_id: str
    pose: Pose4 = Field(
        description="4x4 row-major model -> observation transform, as the answer's pose."
    )
    scale: float
    score: float = Field(description="Its verification score, as the candidates' scores.")
    fitness: float = Field(description="Share of query points within the inlier distance.")
    confidence: float | None = Field(
        description="The probability that this pose is right instead (" + RIGHT_POSE + "); "
        "null when the server's weights have no calibrator."
    )

    @classmethod
    def from_alternative(cls, alternative: Alternative) -> AlternativePublic:
        return cls(
            model_id=alternative.model_id,
            pose=[[float(v) for v in row] for row in alternative.pose],
            scale=scale_of(alternative.pose),
            score=float(alternative.score),
            fitness=float(alternative.fitness),
            confidence=None if alternative.confidence is None else float(alternative.confidence),
        )


class RegisterResponse(BaseModel):
    """The best model for the query, its pose and its inlier statistics."""

    model_id: str
    category: str | None = Field(
        description="The answer's model's category (the request's, when it named one)."
    )
    category_confidence: float | None = Field(
        default=None,
        description="The share of the answers' confidence (the answer's and its "
        "alternatives') that falls on the answer's category: near 1 when no model of another "
        "category came close; 1 when the request named the category. Null without a "
        "calibrator. A ranking signal, not a calibrated probability.",
    )
    symmetry: SymmetryPublic | None = Field(
        default=None,
        description="The answer's model's symmetry about its up: the pose turned about the "
        "model's up by any of these yaws is as right.",
    )
    pose: Pose4 = Field(
        description="4x4 row-major model -> observation transform "
        "(x_obs = pose[:3, :3] @ x_model + pose[:3, 3]); the 3x3 block is scale * R."
    )
    scale: float
    fitness: float = Field(description="Share of query points within the inlier distance.")
    inlier_rmse: float
    num_inliers: int
    inlier_ratio: float
    points_set_aside: int = Field(
        description="Points of the query dropped before registering: those farther than 3 m "
        "from its median (stray sensor returns), the floor under the chair and small clusters "
        "detached from it; the statistics are over the points kept."
    )
    up: Row3 | None = Field(
        description="The up direction (unit, query frame) the pose was searched under: the "
        "request's, or estimated from the cloud when it gave none; null for a free search."
    )
    up_estimated: bool = Field(
        description="True when the request gave no up and the service estimated it."
    )
    confidence: float | None = Field(
        description="The probability that the pose is right, meaning " + RIGHT_POSE + "; "
        "calibrated on views of training chairs. Null when the server's weights have no "
        "calibrator."
    )
    accepted: bool = Field(
        description="False only when the request gave min_confidence and the confidence is "
        "below it or unknown; the answer is then still a 200 with the pose, for the caller to "
        "decide (e.g. to look again from another view)."
    )
    reason: str | None = Field(
        description='Why the answer is not accepted, in a sentence (e.g. "confidence 0.42 is '
        'below min_confidence 0.80: ask for another view"); null when accepted.'
    )
    alternatives: list[AlternativePublic] = Field(
        description="Up to 3 other distinct answers (another model, or the same one turned by "
        "more than 30 degrees, never by one of its symmetric turns), best first; empty when "
        "there are none."
    )
    candidates: list[CandidatePublic] = Field(description="Each model tried, best first.")
    timings_ms: dict[str, float] = Field(
        description="Milliseconds per stage (queue, validate, orient, features, shortlist, "
        "match_ransac, sweep, verify, icp_score, read for files) and the total."
    )
    request_id: str

    @classmethod
    def from_result(
        cls,
        result: RegistrationResult,
        request_id: str,
        *,
        min_confidence: float | None = None,
    ) -> RegisterResponse:
        """The answer to ``result``, accepted or not against the request's ``min_confidence``."""
        confidence = None if result.confidence is None else float(result.confidence)
        accepted, reason = acceptance(confidence, min_confidence)
        return cls(
            model_id=result.model_id,
            category=result.category,
            category_confidence=(
                None if result.category_confidence is None else float(result.category_confidence)
            ),
            symmetry=(
                None if result.symmetry is None else SymmetryPublic.from_symmetry(result.symmetry)
            ),
            pose=[[float(v) for v in row] for row in result.pose],
            scale=result.scale,
            fitness=result.fitness,
            inlier_rmse=result.inlier_rmse,
            num_inliers=result.num_inliers,
            inlier_ratio=result.inlier_ratio,
            points_set_aside=result.points_set_aside,
            up=None if result.up is None else [float(v) for v in result.up],
            up_estimated=result.up_estimated,
            confidence=confidence,
            accepted=accepted,
            reason=reason,
            alternatives=[AlternativePublic.from_alternative(a) for a in result.alternatives],
            candidates=[
                CandidatePublic(model_id=c.model_id, score=c.score) for c in result.candidates
            ],
            timings_ms={k: float(v) for k, v in result.timings_ms.items()},
            request_id=request_id,
        )


class ModelPublic(BaseModel):
    """One library model as callers see it."""

    model_id: str
    category: str = Field(description="The kind of object it is (chair, table...).")
    symmetry: SymmetryPublic = Field(
        description="The turns about its up under which it looks the same, found from its "
        "surface when it was added."
    )
    source: str = Field(
        description="The file it was built from, upload:<file name>, or procedural:<seed>."
    )
    units: str = Field(description="Units the source was declared in (stored in metres).")
    num_points: int
    bbox_min: Vec3
    bbox_max: Vec3
    size: Vec3

    @classmethod
    def from_entry(cls, entry: LibraryEntry) -> ModelPublic:
        return cls.from_record(entry.model_id, entry, entry.symmetry)

    @classmethod
    def of(cls, library: Library, model_id: str) -> ModelPublic:
        """What a loaded library's catalogue says of one of its models (no file read)."""
        return cls.from_record(model_id, library.record(model_id), library.symmetry(model_id))

    @classmethod
    def from_record(
        cls, model_id: str, record: EntryRecord | LibraryEntry, symmetry: YawSymmetry
    ) -> ModelPublic:
        """What the catalogue says of a model (no entry file read)."""
        return cls(
            model_id=model_id,
            category=record.category,
            symmetry=SymmetryPublic.from_symmetry(symmetry),
            source=record.source,
            units=record.units,
            num_points=record.num_points,
            bbox_min=[float(v) for v in record.bbox_min],
            bbox_max=[float(v) for v in record.bbox_max],
            size=[float(v) for v in record.size],
        )


class ModelList(BaseModel):
    count: int = Field(description="Models in this page.")
    total: int = Field(description="Models of the library (of the category asked) in all pages.")
    models: list[ModelPublic]
    categories: dict[str, int] = Field(
        description="How many models of the whole library each category holds."
    )
    next_cursor: str | None = Field(
        description="Pass it as cursor for the next page; null on the last page."
    )


class ModelRemoved(BaseModel):
    removed: str
    count: int = Field(description="Models left in the library.")


class LiveStatus(BaseModel):
    status: Literal["ok"] = "ok"


class ReadyStatus(BaseModel):
    status: Literal["ready", "starting"]


class LibraryInfo(BaseModel):
    path: str
    format_version: int
    models: int
    fingerprint: str
    updated: str
    indexed: int = Field(0, description="Models the shortlist's index holds (library index).")
    unindexed: int = Field(0, description="Models added or changed since, scored one by one.")
    engine: dict[str, JsonData] = Field(
        default_factory=dict,
        description="Engine options the library's catalogue sets (`catalign library configure`); "
        "CATALIGN_ENGINE__<FIELD> variables and `catalign serve --engine` override them.",
    )


class Versions(BaseModel):
    python: str
    torch: str
    open3d: str
    numpy: str


class InfoResponse(BaseModel):
    version: str
    model_card: dict[str, JsonData] = Field(description="The weights' model card.")
    categories: dict[str, list[str]] = Field(
        description="The categories served with networks of their own (``orientation``: up and "
        "heading proposals, ``confidence``: the calibrator), trained on that category's shapes; "
        "every other category is served by the general ones."
    )
    library: LibraryInfo
    voxel_size: float
    headings: int
    engine: EngineConfig = Field(
        description="The engine's options in effect (``headings`` as resolved for the weights): "
        "the library's (`library.engine`) under the CATALIGN_ENGINE__<FIELD> variables and "
        "`catalign serve --engine`."
    )
    versions: Versions


class ErrorDetail(BaseModel):
    code: str = Field(description="Stable machine-readable code, e.g. invalid_input.")
    message: str = Field(description="What was wrong, in words a caller can act on.")


class ErrorResponse(BaseModel):
    """The body of every error answer."""

    error: ErrorDetail
    request_id: str
