"""The package's front door: exported names do not drift, and each one is what it claims."""

from __future__ import annotations

import importlib.metadata

import catalign_client

EXPECTED = {
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
}


def test_exported_names_do_not_drift():
    assert set(catalign_client.__all__) == EXPECTED
    assert catalign_client.__all__ == sorted(catalign_client.__all__)
    assert len(set(catalign_client.__all__)) == len(catalign_client.__all__)
    public = {name for name in dir(catalign_client) if not name.startswith("_")}
    assert public <= EXPECTED, f"public but not exported: {public - EXPECTED}"


def test_every_error_is_a_catalign_error_and_reads_as_public():
    for name in EXPECTED:
        obj = getattr(catalign_client, name)
        if isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, catalign_client.CatalignError), name
        if isinstance(obj, type):
            assert obj.__module__ == "catalign_client", name


def test_version_matches_the_distribution():
    assert catalign_client.__version__ == importlib.metadata.version("catalign-client")
    entry_points = importlib.metadata.entry_points(group="console_scripts")
    assert entry_points["catalign-client"].value == "catalign_client._cli:main"
