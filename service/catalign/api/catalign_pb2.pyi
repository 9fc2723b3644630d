from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RegisterRequest(_message.Message):
    __slots__ = ("points", "top_k", "up", "estimate_scale", "seed", "min_confidence", "category")
    POINTS_FIELD_NUMBER: _ClassVar[int]
    TOP_K_FIELD_NUMBER: _ClassVar[int]
    UP_FIELD_NUMBER: _ClassVar[int]
    ESTIMATE_SCALE_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    MIN_CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    CATEGORY_FIELD_NUMBER: _ClassVar[int]
    points: bytes
    top_k: int
    up: _containers.RepeatedScalarFieldContainer[float]
    estimate_scale: bool
    seed: int
    min_confidence: float
    category: str
    def __init__(self, points: _Optional[bytes] = ..., top_k: _Optional[int] = ..., up: _Optional[_Iterable[float]] = ..., estimate_scale: _Optional[bool] = ..., seed: _Optional[int] = ..., min_confidence: _Optional[float] = ..., category: _Optional[str] = ...) -> None: ...

class Candidate(_message.Message):
    __slots__ = ("model_id", "score")
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    score: float
    def __init__(self, model_id: _Optional[str] = ..., score: _Optional[float] = ...) -> None: ...

class Symmetry(_message.Message):
    __slots__ = ("order", "yaws_deg")
    ORDER_FIELD_NUMBER: _ClassVar[int]
    YAWS_DEG_FIELD_NUMBER: _ClassVar[int]
    order: int
    yaws_deg: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, order: _Optional[int] = ..., yaws_deg: _Optional[_Iterable[float]] = ...) -> None: ...

class Alternative(_message.Message):
    __slots__ = ("model_id", "pose", "scale", "score", "fitness", "confidence")
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    FITNESS_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    pose: _containers.RepeatedScalarFieldContainer[float]
    scale: float
    score: float
    fitness: float
    confidence: float
    def __init__(self, model_id: _Optional[str] = ..., pose: _Optional[_Iterable[float]] = ..., scale: _Optional[float] = ..., score: _Optional[float] = ..., fitness: _Optional[float] = ..., confidence: _Optional[float] = ...) -> None: ...

class RegisterReply(_message.Message):
    __slots__ = ("model_id", "pose", "scale", "fitness", "inlier_rmse", "num_inliers", "inlier_ratio", "candidates", "timings_ms", "request_id", "points_set_aside", "up", "up_estimated", "confidence", "accepted", "reason", "alternatives", "category", "symmetry", "category_confidence")
    class TimingsMsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    FITNESS_FIELD_NUMBER: _ClassVar[int]
    INLIER_RMSE_FIELD_NUMBER: _ClassVar[int]
    NUM_INLIERS_FIELD_NUMBER: _ClassVar[int]
    INLIER_RATIO_FIELD_NUMBER: _ClassVar[int]
    CANDIDATES_FIELD_NUMBER: _ClassVar[int]
    TIMINGS_MS_FIELD_NUMBER: _ClassVar[int]
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    POINTS_SET_ASIDE_FIELD_NUMBER: _ClassVar[int]
    UP_FIELD_NUMBER: _ClassVar[int]
    UP_ESTIMATED_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    ACCEPTED_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    ALTERNATIVES_FIELD_NUMBER: _ClassVar[int]
    CATEGORY_FIELD_NUMBER: _ClassVar[int]
    SYMMETRY_FIELD_NUMBER: _ClassVar[int]
    CATEGORY_CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    pose: _containers.RepeatedScalarFieldContainer[float]
    scale: float
    fitness: float
    inlier_rmse: float
    num_inliers: int
    inlier_ratio: float
    candidates: _containers.RepeatedCompositeFieldContainer[Candidate]
    timings_ms: _containers.ScalarMap[str, float]
    request_id: str
    points_set_aside: int
    up: _containers.RepeatedScalarFieldContainer[float]
    up_estimated: bool
    confidence: float
    accepted: bool
    reason: str
    alternatives: _containers.RepeatedCompositeFieldContainer[Alternative]
    category: str
    symmetry: Symmetry
    category_confidence: float
    def __init__(self, model_id: _Optional[str] = ..., pose: _Optional[_Iterable[float]] = ..., scale: _Optional[float] = ..., fitness: _Optional[float] = ..., inlier_rmse: _Optional[float] = ..., num_inliers: _Optional[int] = ..., inlier_ratio: _Optional[float] = ..., candidates: _Optional[_Iterable[_Union[Candidate, _Mapping]]] = ..., timings_ms: _Optional[_Mapping[str, float]] = ..., request_id: _Optional[str] = ..., points_set_aside: _Optional[int] = ..., up: _Optional[_Iterable[float]] = ..., up_estimated: _Optional[bool] = ..., confidence: _Optional[float] = ..., accepted: _Optional[bool] = ..., reason: _Optional[str] = ..., alternatives: _Optional[_Iterable[_Union[Alternative, _Mapping]]] = ..., category: _Optional[str] = ..., symmetry: _Optional[_Union[Symmetry, _Mapping]] = ..., category_confidence: _Optional[float] = ...) -> None: ...

class ListModelsRequest(_message.Message):
    __slots__ = ("category", "page_size", "page_token")
    CATEGORY_FIELD_NUMBER: _ClassVar[int]
    PAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    category: str
    page_size: int
    page_token: str
    def __init__(self, category: _Optional[str] = ..., page_size: _Optional[int] = ..., page_token: _Optional[str] = ...) -> None: ...

class Model(_message.Message):
    __slots__ = ("model_id", "source", "units", "num_points", "bbox_min", "bbox_max", "size", "category", "symmetry")
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    UNITS_FIELD_NUMBER: _ClassVar[int]
    NUM_POINTS_FIELD_NUMBER: _ClassVar[int]
    BBOX_MIN_FIELD_NUMBER: _ClassVar[int]
    BBOX_MAX_FIELD_NUMBER: _ClassVar[int]
    SIZE_FIELD_NUMBER: _ClassVar[int]
    CATEGORY_FIELD_NUMBER: _ClassVar[int]
    SYMMETRY_FIELD_NUMBER: _ClassVar[int]
    model_id: str
    source: str
    units: str
    num_points: int
    bbox_min: _containers.RepeatedScalarFieldContainer[float]
    bbox_max: _containers.RepeatedScalarFieldContainer[float]
    size: _containers.RepeatedScalarFieldContainer[float]
    category: str
    symmetry: Symmetry
    def __init__(self, model_id: _Optional[str] = ..., source: _Optional[str] = ..., units: _Optional[str] = ..., num_points: _Optional[int] = ..., bbox_min: _Optional[_Iterable[float]] = ..., bbox_max: _Optional[_Iterable[float]] = ..., size: _Optional[_Iterable[float]] = ..., category: _Optional[str] = ..., symmetry: _Optional[_Union[Symmetry, _Mapping]] = ...) -> None: ...

class ListModelsReply(_message.Message):
    __slots__ = ("count", "models", "next_page_token", "total")
    COUNT_FIELD_NUMBER: _ClassVar[int]
    MODELS_FIELD_NUMBER: _ClassVar[int]
    NEXT_PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    count: int
    models: _containers.RepeatedCompositeFieldContainer[Model]
    next_page_token: str
    total: int
    def __init__(self, count: _Optional[int] = ..., models: _Optional[_Iterable[_Union[Model, _Mapping]]] = ..., next_page_token: _Optional[str] = ..., total: _Optional[int] = ...) -> None: ...
