"""Registration methods by name, for the CLI and the evaluation."""

from __future__ import annotations

from collections.abc import Callable

from catalign.errors import ConfigError
from catalign.registration.base import Registrar


def _fpfh() -> Registrar:
    from catalign.registration.fpfh import FPFHRegistrar

    return FPFHRegistrar()


METHODS: dict[str, Callable[[], Registrar]] = {"fpfh": _fpfh}


def build_registrar(name: str) -> Registrar:
    """The registrar called ``name``; an unknown name raises with the list of known ones."""
    try:
        factory = METHODS[name]
    except KeyError:
        raise ConfigError(
            f"unknown method {name!r}; known methods: {', '.join(sorted(METHODS))}"
        ) from None
    return factory()
