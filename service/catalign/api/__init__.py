"""The registration service: FastAPI over HTTP and grpcio over gRPC, on one engine.

``create_app(settings)`` in :mod:`catalign.api.app` builds the app (``catalign serve`` runs it on
uvicorn); :mod:`~catalign.api.settings` holds the configuration, :mod:`~catalign.api.service` the
engine, worker pool and library changes, :mod:`~catalign.api.errors` the one mapping from errors
to HTTP and gRPC statuses, :mod:`~catalign.api.schemas` the public contract.
"""
