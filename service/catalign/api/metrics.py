"""Prometheus metrics of one app instance, kept in its own registry.

A registry per app (not the process-global one) lets tests and tools build several apps in one
process. Labels use the route template (``/models/{model_id}``), never the raw path, so a
caller cannot blow up the number of series.
"""

from __future__ import annotations

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.exposition import CONTENT_TYPE_LATEST

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 25, 60, 120)
RATIO_BUCKETS = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 1.0)
CONTENT_TYPE = CONTENT_TYPE_LATEST


class Metrics:
    """Request, stage, quality and load metrics of the service."""

    def __init__(self) -> None:
        disable_created_metrics()  # no *_created series: they double the output for nothing
        self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter(
            "catalign_http_requests",
            "HTTP requests by method, route and status.",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "catalign_http_request_duration_seconds",
            "HTTP request latency by method, route and status.",
            ["method", "route", "status"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.grpc_requests = Counter(
            "catalign_grpc_requests",
            "gRPC calls by method and status code.",
            ["method", "code"],
            registry=self.registry,
        )
        self.stage = Histogram(
            "catalign_stage_duration_seconds",
            "Time spent in each registration stage (queue wait included).",
            ["stage"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.inlier_ratio = Histogram(
            "catalign_inlier_ratio",
            "Inlier ratio of successful registrations.",
            buckets=RATIO_BUCKETS,
            registry=self.registry,
        )
        self.queue_depth = Gauge(
            "catalign_queue_depth",
            "Admitted jobs waiting for a worker.",
            registry=self.registry,
        )
        self.in_flight = Gauge(
            "catalign_jobs_in_flight",
            "Jobs running on a worker.",
            registry=self.registry,
        )
        self.rejected = Counter(
            "catalign_busy_rejections",
            "Jobs refused because the queue was full.",
            registry=self.registry,
        )
        self.stopped = Counter(
            "catalign_deadline_exceeded",
            "Registrations stopped before their answer: past the deadline (reason=deadline) "
            "or their client went away (reason=client_gone).",
            ["reason"],
            registry=self.registry,
        )
        self.library_models = Gauge(
            "catalign_library_models",
            "Models in the library being served.",
            registry=self.registry,
        )

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        labels = (method, route, str(status))
        self.requests.labels(*labels).inc()
        self.latency.labels(*labels).observe(seconds)

    def observe_registration(self, timings_ms: dict[str, float], inlier_ratio: float) -> None:
        for stage, ms in timings_ms.items():
            self.stage.labels(stage).observe(ms / 1e3)
        self.inlier_ratio.observe(inlier_ratio)

    def render(self) -> bytes:
        return generate_latest(self.registry)
