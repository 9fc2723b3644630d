"""The published contracts match the code: openapi.yaml, typed responses, generated gRPC code."""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import yaml

from catalign.api import codegen
from catalign.api.errors import ERROR_TABLE, kind_of
from catalign.errors import DegenerateInputError, InvalidInputError

ROOT = Path(__file__).resolve().parents[2]


def _export_script() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "export_openapi", ROOT / "scripts/export_openapi.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def openapi() -> dict:
    return yaml.safe_load(_export_script().render())


def test_openapi_yaml_matches_the_app() -> None:
    assert (ROOT / "openapi.yaml").read_text() == _export_script().render(), (
        "openapi.yaml is stale: run python scripts/export_openapi.py"
    )


def test_export_check_exits_1_on_drift(tmp_path: Path) -> None:
    script = _export_script()
    stale = tmp_path / "openapi.yaml"
    stale.write_text("openapi: 3.1.0\n")
    assert script.main(["--check", "--out", str(stale)]) == 1
    assert script.main(["--out", str(stale)]) == 0
    assert script.main(["--check", "--out", str(stale)]) == 0


def _schemas(node: object) -> Iterator[object]:
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("schema", "additionalProperties", "items"):
                yield value
            yield from _schemas(value)
    elif isinstance(node, list):
        for value in node:
            yield from _schemas(value)


def test_every_schema_is_typed(openapi: dict) -> None:
    untyped = [s for s in _schemas(openapi) if s in ({}, True)]
    untyped += [n for n, s in openapi["components"]["schemas"].items() if s in ({}, True)]
    assert not untyped


def test_every_json_answer_is_a_named_model(openapi: dict) -> None:
    for path, item in openapi["paths"].items():
        for method, operation in item.items():
            for status, response in operation["responses"].items():
                for media, content in response.get("content", {}).items():
                    if media == "application/json":
                        assert "$ref" in content["schema"], (method, path, status)


def test_error_codes_are_stable_and_specific() -> None:
    codes = [kind.code for _, kind in ERROR_TABLE]
    assert len(codes) == len(set(codes))
    assert kind_of(DegenerateInputError("flat")).code == "degenerate_input"
    assert kind_of(InvalidInputError("bad")).code == "invalid_input"
    assert kind_of(ValueError("bug")).status == 500


def test_generated_grpc_code_is_current() -> None:
    pytest.importorskip("grpc_tools", reason="grpcio-tools regenerates the gRPC code")
    assert codegen.differences() == [], "run python -m catalign.api.codegen"
