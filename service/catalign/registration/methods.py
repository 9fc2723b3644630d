"""Registration methods by name, for the CLI and the evaluation.

* ``fpfh``: the classic baseline, Open3D's global registration recipe: FPFH at 2.5 cm voxels,
  RANSAC inliers within 1.5 voxels, ICP within 1; rotation-invariant, so it ignores ``up``.
* ``learned``: FCGF features from the trained ResUNet in ``model_store/`` (or ``model_dir``)
  through a real library index and the query :class:`~catalign.registration.engine.Engine`
  (vectorised RANSAC with inliers within 2 voxels, since different instances never match
  exactly; ICP within 1; the up prior when given), with the engine's default configuration
  (:class:`~catalign.registration.config.EngineConfig`: a shortlist of the 10 most similar
  models by global descriptor).
* ``fpfh-engine``: the learned method's index and engine with FPFH features in place of the
  learned ones (one heading: FPFH does not depend on orientation), so that the two features
  are compared with everything else equal.

The two engine methods take an :class:`~catalign.registration.config.EngineConfig` (the
defaults when None); the classic baseline has no engine and refuses one.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from catalign.errors import ConfigError
from catalign.registration.config import EngineConfig
from catalign.registration.results import Registrar


def _fpfh(model_dir: Path | None, up: np.ndarray | None, engine: EngineConfig | None) -> Registrar:
    from catalign.features.extractor import FPFHExtractor
    from catalign.registration.baseline.fpfh import FeatureRegistrar

    extractor = FPFHExtractor()
    voxel = extractor.voxel_size
    return FeatureRegistrar(extractor, name="fpfh", ransac_distance=1.5 * voxel, icp_distance=voxel)


def _learned(
    model_dir: Path | None, up: np.ndarray | None, engine: EngineConfig | None
) -> Registrar:
    from catalign.features.extractor import LearnedExtractor
    from catalign.registration.indexed import IndexedRegistrar

    extractor = LearnedExtractor(model_dir)
    return IndexedRegistrar(extractor, name="learned", up=up, config=engine)


def _fpfh_engine(
    model_dir: Path | None, up: np.ndarray | None, engine: EngineConfig | None
) -> Registrar:
    from catalign.features.extractor import FPFHExtractor
    from catalign.registration.indexed import IndexedRegistrar

    return IndexedRegistrar(FPFHExtractor(), name="fpfh-engine", up=up, config=engine)


METHODS: dict[str, Callable[[Path | None, np.ndarray | None, EngineConfig | None], Registrar]] = {
    "fpfh": _fpfh,
    "learned": _learned,
    "fpfh-engine": _fpfh_engine,
}


def check_method(name: str, engine: EngineConfig | None = None) -> None:
    """Raise :class:`ConfigError` listing the known methods when ``name`` is not one, or when
    ``engine`` options are given to the classic baseline, which has no engine."""
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r}; known methods: {', '.join(sorted(METHODS))}")
    if engine is not None and name == "fpfh":
        raise ConfigError("--engine options apply to learned and fpfh-engine, not to fpfh")


def build_registrar(
    name: str,
    model_dir: Path | None = None,
    up: np.ndarray | None = None,
    engine: EngineConfig | None = None,
) -> Registrar:
    """The registrar called ``name``; ``model_dir`` holds the learned method's weights,
    ``up`` is the world direction of the chair's up axis when known and ``engine`` the
    engine methods' configuration."""
    check_method(name, engine)
    return METHODS[name](model_dir, up, engine)
