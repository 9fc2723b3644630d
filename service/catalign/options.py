"""The base of every group of engine options: a frozen, typed model documented field by field.

Each stage that has tunables declares them as an :class:`OptionGroup` beside its code (the
floor's in :mod:`~catalign.registration.prepare.floor`, the sweep's in
:mod:`~catalign.registration.stages.sweep`...), with the measurement behind each default in the
field's docstring; :class:`~catalign.registration.config.EngineConfig` gathers the groups into
one tree (``engine.floor.max_tilt_deg``), which the service's settings, the command line and the
library's manifest all set. It imports nothing heavy, so any layer may declare a group.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict


def one_line_descriptions(schema: dict[str, Any]) -> None:
    """Docstrings wrap at the source's line length; the JSON schema (``/info``,
    ``openapi.yaml``) gets each as one line."""
    for part in [schema, *schema.get("properties", {}).values()]:
        if "description" in part:
            part["description"] = " ".join(part["description"].split())


class OptionGroup(BaseModel):
    """A group of options: immutable, unknown fields refused (a typo fails loudly), each
    field's docstring its documentation."""

    model_config = ConfigDict(
        extra="forbid",
        frozen=True,
        use_attribute_docstrings=True,
        json_schema_extra=one_line_descriptions,
    )
