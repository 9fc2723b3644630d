"""The live HTTP API against ``openapi.yaml``: schemathesis fuzzes every operation of a server."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from schemathesis import Case, GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.core.failures import FailureGroup
from schemathesis.specs.openapi import checks as oas

from catalign.data.camera import camera_at
from catalign.data.shapes import procedural_shape
from catalign.data.views import render_view, upright_rotation
from catalign.geometry.se3 import make_pose

if TYPE_CHECKING:
    from schemathesis.schemas import APIOperation

    from tests.api.conftest import Server

ROOT = Path(__file__).resolve().parents[2]
KEY = {"X-API-Key": "fuzz-key-0123"}
OCTET = "application/octet-stream"
# Per operation, positive, negative and chair cases together; CATALIGN_FUZZ_EXAMPLES digs deeper,
# and bench/contract.py sends tens of thousands (docs/benchmarks.md, "Contract at volume").
MAX_EXAMPLES = int(os.environ.get("CATALIGN_FUZZ_EXAMPLES", "200"))
VIEW_POINTS = 2000  # a subsampled view keeps each registration well under a second
VIEWS = [(0, 0.7), (1, 2.5), (2, 4.4)]  # (library chair seed, yaw)
CHECKS = [  # no 5xx; status, content type, body and headers as documented; bad input refused
    not_a_server_error,
    *(oas.status_code_conformance, oas.content_type_conformance, oas.response_schema_conformance),
    *(oas.response_headers_conformance, oas.negative_data_rejection, oas.ignored_auth),
]
FUZZ = settings(
    max_examples=MAX_EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate, Phase.shrink],
    suppress_health_check=list(HealthCheck),
)


@functools.cache
def chair_clouds() -> tuple[np.ndarray, ...]:
    """Partial views of the library's chairs, rendered as the conftest's ``chair_view`` does."""
    clouds = []
    for seed, yaw in VIEWS:
        shape = procedural_shape(seed)
        pose = make_pose(upright_rotation(yaw), np.array([0.3, -0.2, -shape.points[:, 1].min()]))
        camera = camera_at(np.array([0.3, -0.2, 0.4]), 2.0, 25.0, 30.0)
        rng = np.random.default_rng(seed)
        points = render_view(shape, pose, camera, rng)
        keep = np.sort(rng.choice(len(points), size=min(VIEW_POINTS, len(points)), replace=False))
        clouds.append(np.ascontiguousarray(points[keep], dtype=np.float32))
    return tuple(clouds)


@dataclass(frozen=True)
class ChairView:
    """``POST /register`` with a real chair view plus fuzzed stray points (often none), as a JSON
    body or as little-endian float32 bytes; its repr names a failing request in the report."""

    view: int
    strays: tuple[tuple[float, float, float], ...]
    binary: bool
    options: dict[str, int | bool]  # seed, estimate_scale and maybe top_k

    def case(self, operation: APIOperation) -> Case:
        points = np.concatenate([chair_clouds()[self.view], np.reshape(self.strays, (-1, 3))])
        if self.binary:
            query = {k: str(v).lower() for k, v in self.options.items()} | {"up": "0,0,1"}
            body = points.astype("<f4").tobytes()
            return operation.Case(body=body, media_type=OCTET, query=query, headers=KEY)
        payload = {"points": points.tolist(), "up": [0, 0, 1], **self.options}
        return operation.Case(body=payload, media_type="application/json", headers=KEY)


COORDINATE = st.floats(allow_nan=False, allow_infinity=False, width=32)
CHAIR_VIEWS = st.builds(
    ChairView,
    st.sampled_from(range(len(VIEWS))),
    st.lists(st.tuples(COORDINATE, COORDINATE, COORDINATE), max_size=3).map(tuple),
    st.booleans(),
    st.fixed_dictionaries(
        {"seed": st.integers(0, 2**31 - 1), "estimate_scale": st.booleans()},
        optional={"top_k": st.integers(1, 10_000)},
    ),
)


def fuzz(operation: APIOperation, chair_statuses: list[int]) -> None:
    """Run ``operation``'s fuzzed cases (plus chair views for ``POST /register``) and checks."""
    options: list[st.SearchStrategy[Case | ChairView]] = [
        operation.as_strategy(mode) for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE)
    ]
    if operation.label == "POST /register":
        options.append(CHAIR_VIEWS)

    @FUZZ
    @given(drawn=st.one_of(options))
    def run(drawn: Case | ChairView) -> None:
        case = drawn.case(operation) if isinstance(drawn, ChairView) else drawn
        try:
            response = case.call_and_validate(checks=CHECKS, timeout=120)
        except (Exception, BaseExceptionGroup) as exc:
            exc.add_note(f"Drawn: {drawn!r}"[:2000])  # schemathesis mutes hypothesis's own
            raise
        if isinstance(drawn, ChairView):
            chair_statuses.append(response.status_code)

    run()


def describe(exc: BaseException) -> str:
    """Every failure hypothesis found, with the request that reproduces it."""
    if isinstance(exc, BaseExceptionGroup) and not isinstance(exc, FailureGroup):
        return "\n".join(describe(inner) for inner in exc.exceptions)
    return "\n".join([f"{type(exc).__name__}: {exc}", *getattr(exc, "__notes__", [])])


@pytest.mark.slow
def test_api_honours_openapi_under_fuzzing(
    serve: Callable[..., AbstractContextManager[Server]], library_copy: Path
) -> None:
    """Fuzzed requests (valid, invalid, and real chair views among the ``POST /register`` bodies)
    to every operation of a live server with an API key never get a 5xx; every answer has a
    documented status, content type, headers and body; invalid input is refused; the key is
    enforced; and the chair views reach the engine and are registered (200)."""
    schema = schemathesis.openapi.from_path(ROOT / "openapi.yaml")
    failures: dict[str, str] = {}
    chair_statuses: list[int] = []
    with serve(library=library_copy, api_key=KEY["X-API-Key"]) as server:
        schema.config.update(base_url=server.url, headers=KEY)
        for result in schema.get_all_operations():
            operation = result.ok()
            try:
                fuzz(operation, chair_statuses)
            except (Exception, BaseExceptionGroup) as exc:  # fuzz every operation, then report
                failures[operation.label] = describe(exc)
    assert not failures, "\n\n".join(f"== {label}\n{text}" for label, text in failures.items())
    assert 200 in chair_statuses, f"no chair view was registered: {chair_statuses}"
