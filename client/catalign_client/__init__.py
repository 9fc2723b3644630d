"""Thin Python SDK for the catalign registration service (httpx and numpy only).

A robot sends a partial point cloud of a chair and gets back the best CAD model of the server's
library, its SE(3) pose and inlier statistics, without installing torch or open3d::

    import numpy as np
    from catalign_client import AlignResult, AsyncClient, Client, InvalidInputError

    points = np.load("chair_view.npy")              # (N, 3); or Open3D, trimesh, PointCloud2
    with Client("http://localhost:8000", api_key="secret") as client:
        if not client.health():
            raise SystemExit("catalign is still starting")
        try:
            result = client.align(points, up=(0, 0, 1), seed=0, min_confidence=0.8)
        except InvalidInputError as error:          # 422: fix the points, do not retry
            print(error.code, error.message, error.request_id)
            raise
        print(result.model_id, result.fitness, result.confidence)  # confidence: None or 0..1
        if not result.accepted:                     # below min_confidence: the pose is still
            print(result.reason)                    # there; e.g. look from another side
        R, t = result.rotation, result.translation  # x_obs = scale * R @ x_model + t
        pose = result.pose                          # numpy (4, 4) float64
        model = client.model_points(result.model_id)  # (M, 3) surface points, model frame
        result.plot(points, model, "alignment.png")   # needs catalign-client[plot]

    # asyncio: the same methods, awaited
    async def locate(points: np.ndarray) -> AlignResult:
        async with AsyncClient("http://localhost:8000") as client:
            return await client.align(points)

From a shell: ``catalign-client align cloud.ply --url http://localhost:8000`` prints the result
as JSON (``--png out.png`` also draws it); ``catalign-client models --url ...`` lists the library.
"""

from ._client import AsyncClient, Client
from ._exceptions import (
    APIError,
    AuthenticationError,
    CatalignError,
    ConflictError,
    DecodingError,
    DegenerateInputError,
    InvalidInputError,
    InvalidPointsError,
    NotFoundError,
    PayloadTooLargeError,
    PermissionDeniedError,
    ServerError,
    ServiceUnavailableError,
    TransportError,
)
from ._models import AlignResult, Alternative, Candidate, ModelInfo, Symmetry
from ._pointcloud2 import PointCloud2Like
from ._points import HasPoints, HasVertices, PointsLike
from ._version import __version__

__all__ = [
    "APIError",
    "AlignResult",
    "Alternative",
    "AsyncClient",
    "AuthenticationError",
    "Candidate",
    "CatalignError",
    "Client",
    "ConflictError",
    "DecodingError",
    "DegenerateInputError",
    "HasPoints",
    "HasVertices",
    "InvalidInputError",
    "InvalidPointsError",
    "ModelInfo",
    "NotFoundError",
    "PayloadTooLargeError",
    "PermissionDeniedError",
    "PointCloud2Like",
    "PointsLike",
    "ServerError",
    "ServiceUnavailableError",
    "Symmetry",
    "TransportError",
    "__version__",
]

# Errors and results read as public classes in tracebacks and reprs, not private modules.
for _name in __all__:
    _obj = globals()[_name]
    if isinstance(_obj, type):
        _obj.__module__ = __name__
del _name, _obj
