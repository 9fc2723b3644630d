"""A :class:`Registrar` over a real library index, so evaluation exercises the service's path.

``prepare`` writes the given shapes as files (a mesh as ``.ply``, points as ``.npy``), builds an
index from them with the extractor (the same code as ``catalign library build``), loads it with
its checks, and puts an :class:`~catalign.registration.engine.Engine` on top; ``register``
forwards to the engine.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from catalign.features.extractor import FeatureExtractor
from catalign.library.index import build
from catalign.library.loaded import load
from catalign.registration.config import EngineConfig
from catalign.registration.decision.confidence import Calibrator
from catalign.registration.engine import FROM_WEIGHTS, Engine, FromWeights
from catalign.registration.results import LibraryShape, Registrar, RegistrationResult


class IndexedRegistrar(Registrar):
    """The engine, prepared from in-memory shapes through an on-disk index; ``config`` is the
    engine's (its defaults when not given), ``up`` the world's up direction when known,
    ``calibrator`` the engine's (by default the one beside the extractor's weights)."""

    def __init__(
        self,
        extractor: FeatureExtractor,
        *,
        name: str,
        up: np.ndarray | None = None,
        config: EngineConfig | None = None,
        calibrator: Calibrator | FromWeights | None = FROM_WEIGHTS,
    ) -> None:
        self.extractor = extractor
        self.calibrator = calibrator
        self.name = name
        self.up = up
        self.config = config
        self.engine: Engine | None = None

    def prepare(self, library: Sequence[LibraryShape]) -> None:
        with tempfile.TemporaryDirectory(prefix="catalign-eval-") as folder:
            sources = Path(folder) / "sources"
            for shape in library:  # one sub-folder per category: the build names them so
                place = sources / shape.category
                place.mkdir(parents=True, exist_ok=True)
                if shape.mesh is None:
                    np.save(place / f"{shape.model_id}.npy", shape.points.astype(np.float32))
                else:
                    mesh = trimesh.Trimesh(shape.mesh.vertices, shape.mesh.faces, process=False)
                    mesh.export(place / f"{shape.model_id}.ply")
            build([sources], Path(folder) / "index", self.extractor, progress=False)
            index = load(Path(folder) / "index", self.extractor.fingerprint).in_memory()
        self.engine = Engine(self.extractor, index, config=self.config, calibrator=self.calibrator)

    def register(
        self, points: np.ndarray, *, seed: int = 0, category: str | None = None
    ) -> RegistrationResult:
        if self.engine is None:
            raise RuntimeError("prepare() the registrar with a library before registering")
        return self.engine.register(points, up=self.up, seed=seed, category=category)
