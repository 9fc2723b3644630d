"""The service's configuration: one typed settings class, read from ``CATALIGN_*`` variables.

Every knob of ``catalign serve`` lives here, validated once at the edge (a bad port or a zero
queue fails at start-up with a sentence, not at the first request); command-line flags are passed
as keyword arguments and so override the environment. The engine's options are one nested
:class:`~catalign.registration.config.EngineConfig`, set as ``CATALIGN_ENGINE__<FIELD>``
(``CATALIGN_ENGINE__TOP_K=5``). Nothing below the API layer sees this class:
:class:`~catalign.api.service.RegistrationService` turns it into plain arguments and the
engine's configuration.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.config import EngineConfig

MiB = 1 << 20
# Variables that moved: refused with their new name rather than silently ignored.
RENAMED = {"CATALIGN_TOP_K": "CATALIGN_ENGINE__TOP_K"}
# What Kubernetes (and Docker's legacy links) put in <SERVICE>_PORT: tcp://10.0.0.1:8000.
SERVICE_LINK = re.compile(r"(tcp|udp|sctp)://[^\s/]+:[0-9]+", re.IGNORECASE)


class ServiceSettings(BaseSettings):
    """Settings of the HTTP and gRPC service (environment prefix ``CATALIGN_``).

    ``workers`` workers run registrations, each in its own process with its own engine
    (``worker_processes``, the default: threads of one process wait for each other's GIL) or
    as threads sharing the server's engine, each with ``threads_per_worker`` threads for torch,
    BLAS, OpenMP and Open3D (default: an even share of the cores the process may run on, capped
    by the container's cgroup CPU limit, see :func:`catalign.threads.cores`); ``queue`` more
    requests may wait for one, and any request beyond that is refused at once with 503
    ``busy``. Each registration must finish within ``deadline_s`` of its arrival (queue wait
    included), or it is stopped and answered 503 ``deadline_exceeded``. ``max_body_bytes``
    bounds every request body, ``max_points`` every query cloud and every uploaded file. Uploads
    are spooled under ``spool_dir`` (default: the library's ``.spool`` folder, or the system's
    temporary folder when the library is read-only). ``api_key`` (or the first line of
    ``api_key_file``), when set, is required in the ``X-API-Key`` header (gRPC: ``x-api-key``
    metadata) by every endpoint but the health checks; ``Authorization: Bearer <key>`` (gRPC:
    ``authorization`` metadata) is accepted too, for clients that cannot set a custom header.
    ``engine`` holds the registration engine's options, the default shortlist size ``top_k``
    among them (``CATALIGN_ENGINE__TOP_K``).

    A setting whose value has the form ``tcp://host:port`` (also ``udp://``, ``sctp://``) is
    refused at start-up, naming the variable: it is a Kubernetes service-link variable, which a
    Service named ``catalign`` (``CATALIGN_PORT``) or ``catalign-grpc`` (``CATALIGN_GRPC_PORT``)
    injects into every pod of its namespace unless the pod sets ``enableServiceLinks: false``.
    It is refused rather than ignored because no setting is ever meant to hold such a value: one
    that does was either injected (turn service links off, or rename the Service) or written by
    mistake for a port, and in both cases starting on a default port would hide the problem.
    """

    model_config = SettingsConfigDict(
        env_prefix="CATALIGN_",
        env_nested_delimiter="__",
        env_parse_none_str="none",  # CATALIGN_ENGINE__MODEL_POINTS=none: every key point
        extra="forbid",
        frozen=True,
    )

    library: Path = Field(default=DEFAULT_MODEL_DIR / "library", description="Library folder.")
    model_dir: Path = Field(default=DEFAULT_MODEL_DIR, description="Extractor weights folder.")
    host: str = Field(default="127.0.0.1", min_length=1)
    port: int = Field(default=8000, ge=1, le=65535)
    grpc_port: int = Field(default=50051, ge=0, le=65535, description="0 disables gRPC.")
    workers: int = Field(default=2, ge=1, le=64, description="Registration workers.")
    worker_processes: bool = Field(
        default=True,
        description="Run each worker's registrations in its own process (one engine each; "
        "threads share one engine and its GIL).",
    )
    queue: int = Field(default=8, ge=0, le=10_000, description="Requests that may wait.")
    threads_per_worker: int | None = Field(
        default=None, ge=1, le=256, description="Numeric threads per worker (None: cores/workers)."
    )
    deadline_s: float = Field(default=10.0, gt=0, le=3600, description="Per-request deadline.")
    spool_dir: Path | None = Field(default=None, description="Where uploads are spooled.")
    api_key: SecretStr | None = None
    api_key_file: Path | None = Field(default=None, description="A file holding the API key.")
    read_only: bool = False
    max_body_bytes: int = Field(default=64 * MiB, ge=1024, description="Request body limit.")
    max_points: int = Field(default=500_000, ge=1, description="Points a query may have.")
    engine: EngineConfig = Field(default_factory=EngineConfig, description="Engine options.")
    warmup: bool = Field(default=True, description="Run one registration before ready.")
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @model_validator(mode="before")
    @classmethod
    def _no_renamed_variables(cls, data: object) -> object:
        for old, new in RENAMED.items():
            if old in os.environ:
                raise ValueError(f"{old} is now {new}; rename it in the environment")
        return data

    @model_validator(mode="before")
    @classmethod
    def _no_service_link_values(cls, data: object) -> object:
        if not isinstance(data, dict):
            return data
        for field, value in data.items():
            secret = field == "api_key"  # any printable key is allowed, and never echoed
            if not secret and isinstance(value, str) and SERVICE_LINK.fullmatch(value.strip()):
                raise ValueError(_service_link_message(str(field), value.strip()))
        return data

    @field_validator("api_key")
    @classmethod
    def _key_is_usable(cls, value: SecretStr | None) -> SecretStr | None:
        if value is None:
            return None
        key = value.get_secret_value()
        if len(key) < 8 or key != key.strip() or not key.isprintable():
            raise ValueError("an API key needs at least 8 printable characters, no outer spaces")
        return value

    @model_validator(mode="after")
    def _key_from_file(self) -> ServiceSettings:
        if self.api_key_file is None:
            return self
        if self.api_key is not None:
            raise ValueError("give the API key once: api_key or api_key_file, not both")
        try:
            lines = self.api_key_file.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as error:
            raise ValueError(f"cannot read the API key file {self.api_key_file}: {error}") from None
        key = SecretStr(lines[0] if lines else "")
        object.__setattr__(self, "api_key", self._key_is_usable(key))
        return self

    @field_validator("host")
    @classmethod
    def _host_has_no_scheme(cls, value: str) -> str:
        if "://" in value or "/" in value:
            raise ValueError(f"host must be a name or address, not a URL: {value!r}")
        return value

    @model_validator(mode="after")
    def _ports_differ(self) -> ServiceSettings:
        if self.grpc_port == self.port:
            raise ValueError(f"port and grpc_port are both {self.port}; give gRPC another port")
        return self

    @property
    def grpc_enabled(self) -> bool:
        return self.grpc_port != 0

    @property
    def worker_threads(self) -> int:
        """Numeric threads of each worker: the setting, or an even share of the cores."""
        from catalign.threads import default_threads_per_worker

        return self.threads_per_worker or default_threads_per_worker(self.workers)

    @property
    def capacity(self) -> int:
        """Requests admitted at once: running plus waiting."""
        return self.workers + self.queue


def _service_link_message(field: str, value: str) -> str:
    """One sentence on a service-link value in ``field``, naming the variable that holds it."""
    wanted = f"CATALIGN_{field}".upper()
    variable = next((name for name in os.environ if name.upper() == wanted), wanted)
    service = ""
    if variable.upper().endswith("_PORT"):
        service = f" named {variable[: -len('_PORT')].lower().replace('_', '-')}"
    return (
        f"{variable}={value} is a Kubernetes service-link variable (the address of a Service"
        f"{service}), not a setting: set `enableServiceLinks: false` in the pod spec or rename "
        "the Service"
    )
