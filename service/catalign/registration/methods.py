"""Registration methods by name, for the CLI and the evaluation."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from catalign.errors import ConfigError
from catalign.registration.base import Registrar


def _fpfh(model_dir: Path | None) -> Registrar:
    from catalign.registration.fpfh import FPFHRegistrar

    return FPFHRegistrar()


def _learned(model_dir: Path | None) -> Registrar:
    from catalign.registration.learned import LearnedRegistrar

    return LearnedRegistrar(model_dir)


METHODS: dict[str, Callable[[Path | None], Registrar]] = {"fpfh": _fpfh, "learned": _learned}


def check_method(name: str) -> None:
    """Raise :class:`ConfigError` listing the known methods when ``name`` is not one."""
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r}; known methods: {', '.join(sorted(METHODS))}")


def build_registrar(name: str, model_dir: Path | None = None) -> Registrar:
    """The registrar called ``name`` (``model_dir``: weights of the learned method)."""
    check_method(name)
    return METHODS[name](model_dir)
