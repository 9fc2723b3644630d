"""``catalign calibrate``: fit the answers' confidence on views of the *training* chairs.

The validation chairs stay untouched for measuring the calibration. The training chairs play
both of the evaluation's settings: *same* (the library holds every training chair, so the
observed one's CAD is in it) and *cross* (the chairs split in :data:`CROSS_FOLDS` folds by
sorted id, each fold's views registered against a library of the other folds: 46 of the 61
training chairs, near the 61 the evaluation's *cross* library holds). Views come upright with ``up``
given and in any rotation without it, so the calibrator learns what an estimated up costs.
Every answer, the winner and its alternatives, is one sample: its
:class:`~catalign.registration.decision.confidence.Evidence` and whether it is right (within 10
degrees and 5 cm in the evaluation's category-level metric). Gradient-boosted trees (scikit-learn's
``GradientBoostingClassifier``, :data:`BOOSTING`) on the signals are the calibrator, exported as
plain arrays (:class:`~catalign.registration.decision.confidence.Tree`); its card records the
command, the data, the signals' importances and its in-sample quality.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from catalign.data.shapes import Shape
from catalign.data.views import WORLD_UP
from catalign.errors import ConfigError, InvalidInputError
from catalign.evaluation.metrics import (
    auroc,
    canonical_pose_error,
    expected_calibration_error,
    is_right,
)
from catalign.evaluation.protocol import (
    TestCase,
    build_cases,
    frames_of,
    metric_shapes,
    symmetries_of,
)
from catalign.features.extractor import FeatureExtractor
from catalign.geometry.ncc import NCCFrame
from catalign.geometry.symmetry import NO_SYMMETRY, YawSymmetry
from catalign.registration.decision.confidence import (
    CALIBRATOR_FILE,
    SIGNALS,
    Calibrator,
    Evidence,
    Tree,
)
from catalign.registration.indexed import IndexedRegistrar
from catalign.registration.results import LibraryShape, RegistrationResult
from catalign.training.config import CalibrationConfig
from catalign.training.loop import ShapeSource

SAMPLES_FILE = "samples.npz"
# The trees: 200 of depth 3 (8 leaves at most), each leaf holding 20 answers or more. Set before
# they were scored; two other shapes scored within 0.01 of them on average on the validation
# views (``bench/calibrators.py``).
BOOSTING = {
    "n_estimators": 200,
    "learning_rate": 0.05,
    "max_depth": 3,
    "max_leaf_nodes": 8,
    "min_samples_leaf": 20,
    "random_state": 0,
}
# Folds of the *cross* setting: the more, the closer each library's size to the evaluation's
# (a larger library offers more near misses, so an answer is less often right).
CROSS_FOLDS = 4


@dataclass
class Samples:
    """Answers and their labels: one row of :data:`SIGNALS` per answer, whether it is right,
    its kind (``"<mode>[-fused]/<setting>/<winner|alternative>"``, ``-fused`` for a
    reconstruction) and the chair it is a view of.
    Saved beside the calibrator (``samples.npz``) so that it can be refitted without
    registering the views again (``catalign calibrate --samples``)."""

    rows: list[list[float]] = field(default_factory=list)
    right: list[bool] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    chairs: list[str] = field(default_factory=list)

    def add(self, evidence: Evidence, right: bool, kind: str, chair: str) -> None:
        self.rows.append(evidence.row())
        self.right.append(right)
        self.kinds.append(kind)
        self.chairs.append(chair)

    def matrix(self) -> np.ndarray:
        return np.asarray(self.rows, dtype=np.float64).reshape(-1, len(SIGNALS))

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            signals=np.array(SIGNALS),
            rows=self.matrix(),
            right=np.array(self.right),
            kinds=np.array(self.kinds),
            chairs=np.array(self.chairs),
        )

    def extend(self, other: Samples) -> None:
        self.rows += other.rows
        self.right += other.right
        self.kinds += other.kinds
        self.chairs += other.chairs

    @classmethod
    def load(cls, path: Path) -> Samples:
        """Samples saved by :meth:`save`; a clear error when their signals are not this
        code's."""
        try:
            data = np.load(path)
        except (OSError, ValueError) as error:
            raise ConfigError(f"cannot read calibration samples {path}: {error}") from None
        if data["signals"].tolist() != list(SIGNALS):
            raise ConfigError(f"the samples {path} hold other signals; collect them again")
        return cls(
            rows=data["rows"].tolist(),
            right=data["right"].tolist(),
            kinds=data["kinds"].tolist(),
            chairs=data["chairs"].tolist(),
        )


def right_pose(
    pose: np.ndarray,
    model_id: str,
    case: TestCase,
    frames: dict[str, NCCFrame],
    symmetries: Mapping[str, YawSymmetry] | None = None,
) -> bool:
    """Whether a pose of ``model_id`` is right by the evaluation's criterion (to the nearest
    pose equivalent under the observed shape's symmetry, in ``symmetries``)."""
    symmetry = (symmetries or {}).get(case.shape_id, NO_SYMMETRY)
    error = canonical_pose_error(pose, frames[model_id], case.pose, frames[case.shape_id], symmetry)
    return is_right(error)


def label(
    result: RegistrationResult,
    case: TestCase,
    frames: dict[str, NCCFrame],
    samples: Samples,
    kind: str,
    symmetries: Mapping[str, YawSymmetry] | None = None,
) -> None:
    """Add the winner and each alternative of ``result`` to ``samples``."""
    answers = [(result.evidence, result.pose, result.model_id, "winner")]
    answers += [(a.evidence, a.pose, a.model_id, "alternative") for a in result.alternatives]
    for evidence, pose, model_id, rank in answers:
        if evidence is not None:
            right = right_pose(pose, model_id, case, frames, symmetries)
            samples.add(evidence, right, f"{kind}/{rank}", case.shape_id)


def plans(ids: list[str]) -> list[tuple[list[str], list[str], str]]:
    """``(library ids, observed ids, setting)`` of the calibration's registrations: *same*
    (every chair in the library), then each of :data:`CROSS_FOLDS` folds against a library of
    the others (*cross*)."""
    folds = [ids[k::CROSS_FOLDS] for k in range(CROSS_FOLDS)]
    found = [(ids, ids, "same")]
    return found + [([i for i in ids if i not in fold], fold, "cross") for fold in folds if fold]


def collect(
    config: CalibrationConfig,
    shapes: dict[str, Shape],
    extractor: FeatureExtractor,
    progress: bool = True,
) -> Samples:
    """Register views of ``shapes`` in both settings and every pose mode; label the answers."""
    frames, symmetries = frames_of(shapes), symmetries_of(shapes)
    samples = Samples()
    for library_ids, observed_ids, setting in plans(sorted(shapes)):
        registrar = IndexedRegistrar(extractor, name="learned")
        registrar.prepare([LibraryShape(i, shapes[i].points, shapes[i].mesh) for i in library_ids])
        assert registrar.engine is not None
        observed = {i: shapes[i] for i in observed_ids}
        for mode in config.pose_modes:
            up = WORLD_UP if mode == "upright" else None
            for source, views in (("single", config.views), ("fused", config.fused_views)):
                name = mode if source == "single" else f"{mode}-fused"
                cases = build_cases(observed, views, config.seed, mode, source=source)
                for case in tqdm(cases, desc=f"calibrate {setting} {name}", disable=not progress):
                    try:
                        result = registrar.engine.register(case.points, up=up, seed=config.seed)
                    except InvalidInputError:
                        continue  # a refused view has no answer to calibrate
                    label(result, case, frames, samples, f"{name}/{setting}", symmetries)
    return samples


def fit(samples: Samples, **changes: Any) -> Calibrator:
    """Boosted trees on the signals (:data:`BOOSTING`, with ``changes`` to its settings: the
    other shapes ``bench/calibrators.py`` compares), exported to a
    :class:`~catalign.registration.decision.confidence.Calibrator` whose card names the settings and
    each signal's importance."""
    from sklearn.ensemble import GradientBoostingClassifier

    x, y = samples.matrix(), np.array(samples.right, dtype=bool)
    if len(set(y.tolist())) < 2:
        raise ValueError("calibration needs both right and wrong answers; use more views")
    settings = BOOSTING | changes
    model = GradientBoostingClassifier(**settings).fit(x, y)
    trees = tuple(
        Tree(
            feature=tree.feature.astype(np.int64),
            threshold=tree.threshold.copy(),
            left=tree.children_left.astype(np.int64),
            right=tree.children_right.astype(np.int64),
            value=tree.value[:, 0, 0].copy(),
        )
        for tree in (estimator.tree_ for estimator in model.estimators_[:, 0])
    )
    # The log-odds every tree adds to: the prior's, as scikit-learn starts from it.
    baseline = float(np.log(y.mean() / (1.0 - y.mean())))
    importances = dict(zip(SIGNALS, model.feature_importances_.round(4).tolist(), strict=True))
    card = {"boosting": settings, "importances": importances}
    return Calibrator(baseline, float(model.learning_rate), trees, card=card)


def calibration_quality(probabilities: Sequence[float], right: Sequence[bool]) -> dict[str, Any]:
    """Expected calibration error (10 bins), AUROC of right against wrong, the share right."""
    p, y = np.asarray(probabilities, dtype=float), np.asarray(right, dtype=bool)
    return {
        "ece": expected_calibration_error(p, y),
        "auroc": auroc(p, y),
        "right": float(y.mean()),
        "count": len(y),
    }


def run(
    config: CalibrationConfig,
    chairs: ShapeSource,
    extractor: FeatureExtractor | None,
    progress: bool = True,
    samples_files: Sequence[Path] = (),
) -> Calibrator:
    """Collect samples on the training shapes of ``chairs`` (chairs or tables) with
    ``extractor`` (or read and join
    ``samples_files``: single views from one run, reconstructions from another), fit, and save
    the calibrator and its samples to ``config.out``."""
    started = time.perf_counter()
    if samples_files:
        samples = Samples()
        for path in samples_files:
            samples.extend(Samples.load(path))
        source = "samples read from " + ", ".join(str(p) for p in samples_files)
    elif extractor is None:
        raise ConfigError("calibration needs weights to register views, or --samples")
    else:
        ids = list(chairs.ids("train"))
        ids = ids if config.max_shapes is None else ids[: config.max_shapes]
        samples = collect(config, metric_shapes(chairs, ids), extractor, progress)
        source = f"{len(ids)} training {chairs.category}s of the split (validation untouched)"
    samples.save(config.out / SAMPLES_FILE)
    fitted = fit(samples)
    probabilities = fitted.probabilities(samples.matrix())
    winners = np.array([k.endswith("winner") for k in samples.kinds])
    right = np.array(samples.right, dtype=bool)
    card: dict[str, Any] = {
        "command": config.command() + "".join(f" --samples {p}" for p in samples_files),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "seconds": round(time.perf_counter() - started, 1),
        "data": {
            "chairs": source,
            "chair_ids": sorted(set(samples.chairs)),
            **_collection(config, samples_files),
            "answers": len(samples.right),
            "by_kind": {k: samples.kinds.count(k) for k in sorted(set(samples.kinds))},
        },
        "right_means": "within 10 degrees and 5 cm (category-level metric)",
        "in_sample": calibration_quality(probabilities, right),
        "in_sample_winners": calibration_quality(probabilities[winners], right[winners]),
    } | fitted.card
    calibrator = replace(fitted, card=card)
    calibrator.save(config.out)
    return calibrator


def _collection(config: CalibrationConfig, samples_files: Sequence[Path]) -> dict[str, Any]:
    """How the samples were collected: this run's views, seed and modes, or, for a refit,
    the commands of the runs that collected them (their cards beside the samples)."""
    if not samples_files:
        return {
            "views": config.views,
            "fused_views": config.fused_views,
            "seed": config.seed,
            "pose_modes": list(config.pose_modes),
        }
    collected = []
    for path in samples_files:
        card_path = path.parent / CALIBRATOR_FILE
        if not card_path.is_file():
            collected.append(f"unknown (no {CALIBRATOR_FILE} beside {path})")
            continue
        card = json.loads(card_path.read_text()).get("card", {})
        collected.append(card.get("command", "unknown"))
    return {"collected_by": collected}
