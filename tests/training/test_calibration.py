"""``catalign calibrate`` on a tiny set writes a calibrator that the engine then applies."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from catalign.cli import app
from catalign.data.shapes import SharedChairs, SharedTables, split_of, to_metric
from catalign.data.views import WORLD_UP
from catalign.evaluation.protocol import build_cases
from catalign.features.extractor import DEFAULT_MODEL_DIR, LearnedExtractor
from catalign.registration.decision.confidence import (
    SIGNALS,
    Calibrator,
    find_calibrator,
    find_category_calibrators,
)
from catalign.registration.indexed import IndexedRegistrar
from catalign.registration.results import LibraryShape
from catalign.training.calibration import BOOSTING, Samples, fit, plans

runner = CliRunner()


@pytest.mark.slow
def test_a_tiny_calibration_writes_a_calibrator_the_engine_applies(
    chairs_root: Path, tmp_path: Path
) -> None:
    if not (DEFAULT_MODEL_DIR / "model.safetensors").is_file():
        pytest.skip("model_store/ has no trained weights")
    out = tmp_path / "weights" / "confidence"
    args = ["calibrate", "--out", str(out), "--views", "1", "--max-shapes", "4"]
    result = runner.invoke(app, [*args, "--pose-mode", "upright", "--chairs-dir", str(chairs_root)])
    assert result.exit_code == 0, result.output
    assert "calibrator written" in result.output

    calibrator = find_calibrator(out.parent)
    assert calibrator is not None
    card = calibrator.card
    assert card["command"].startswith("catalign calibrate")
    assert card["data"]["answers"] >= 4 and card["data"]["pose_modes"] == ["upright"]
    assert set(card["importances"]) == set(SIGNALS)
    assert 0.0 <= card["in_sample"]["ece"] <= 1.0

    # Its samples are saved beside it: a refit from them needs no views and fits the same.
    again = tmp_path / "again"
    samples = str(out / "samples.npz")
    refit = runner.invoke(app, ["calibrate", "--out", str(again), "--samples", samples])
    assert refit.exit_code == 0, refit.output
    refitted = Calibrator.load(again / "calibrator.json")
    rows = Samples.load(out / "samples.npz").matrix()
    np.testing.assert_allclose(refitted.probabilities(rows), calibrator.probabilities(rows))

    # Reconstructions are collected beside (or instead of) single views, and a refit joins the
    # samples of several runs.
    fused = tmp_path / "fused"
    args = ["calibrate", "--out", str(fused), "--views", "0", "--fused-views", "1"]
    args += ["--max-shapes", "4", "--pose-mode", "upright", "--chairs-dir", str(chairs_root)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    fused_kinds = set(Samples.load(fused / "samples.npz").kinds)
    assert fused_kinds and all(k.startswith("upright-fused/") for k in fused_kinds)
    joined = tmp_path / "joined"
    both = ["--samples", samples, "--samples", str(fused / "samples.npz")]
    refit = runner.invoke(app, ["calibrate", "--out", str(joined), *both])
    assert refit.exit_code == 0, refit.output
    kinds = set(Samples.load(joined / "samples.npz").kinds)
    assert fused_kinds < kinds and any(k.startswith("upright/") for k in kinds)
    assert len(Calibrator.load(joined / "calibrator.json").card["data"]["collected_by"]) == 2

    # Given to the engine, it gives every answer a probability.
    extractor = LearnedExtractor()
    chairs = SharedChairs(chairs_root)
    shapes = {i: to_metric(chairs.load(i)) for i in chairs.ids("val")[:2]}
    registrar = IndexedRegistrar(extractor, name="learned", up=WORLD_UP, calibrator=calibrator)
    registrar.prepare([LibraryShape(i, s.points) for i, s in shapes.items()])
    case = build_cases(shapes, 1, seed=5)[0]
    answer = registrar.register(case.points, seed=0)
    assert answer.confidence is not None and 0.0 <= answer.confidence <= 1.0
    assert all(0.0 <= a.confidence <= 1.0 for a in answer.alternatives)
    assert answer.confidence == pytest.approx(calibrator.probability(answer.evidence))


def test_calibrate_refuses_an_unknown_pose_mode_with_a_sentence(tmp_path: Path) -> None:
    result = runner.invoke(app, ["calibrate", "--out", str(tmp_path), "--pose-mode", "tilted"])
    assert result.exit_code == 2
    assert "unknown pose mode 'tilted'" in result.output
    assert not list(tmp_path.iterdir())


def test_the_shipped_calibrator_matches_this_code_and_saw_no_validation_chair() -> None:
    path = DEFAULT_MODEL_DIR / "confidence" / "calibrator.json"
    if not path.is_file():
        pytest.skip("model_store/ ships no confidence calibrator")
    data = json.loads(path.read_text())
    assert data["signals"] == list(SIGNALS)
    assert len(Calibrator.load(path).trees) == data["card"]["boosting"]["n_estimators"]
    chairs = data["card"]["data"]["chair_ids"]
    assert len(chairs) >= 50
    assert all(split_of(chair) == "train" for chair in chairs)  # never a validation chair


def test_calibrate_refuses_zero_views_of_either_kind_with_a_sentence(tmp_path: Path) -> None:
    args = ["calibrate", "--out", str(tmp_path), "--views", "0", "--fused-views", "0"]
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert "nothing to fit on" in result.output


def test_every_training_chair_is_observed_once_in_each_setting() -> None:
    ids = [f"chair{i:02d}" for i in range(61)]
    found = plans(ids)
    for setting in ("same", "cross"):
        observed = [i for _, seen, s in found if s == setting for i in seen]
        assert sorted(observed) == ids, setting
    for library, seen, setting in found:
        # *same*: the observed chairs' own CAD is in the library (every training chair);
        # *cross*: none is, in a library near the evaluation's 61.
        inside = set(seen) <= set(library) if setting == "same" else not set(seen) & set(library)
        assert inside, setting
        assert len(library) in ((61,) if setting == "same" else (45, 46)), setting


def test_the_exported_trees_give_scikit_learns_probabilities() -> None:
    """The calibrator walks the trees itself (no scikit-learn at query time): it must agree
    with the fitted model it was exported from, on the samples and on new rows."""
    from sklearn.ensemble import GradientBoostingClassifier

    rng = np.random.default_rng(0)
    samples = Samples()
    rows = rng.uniform(0.0, 1.0, size=(400, len(SIGNALS)))
    right = rows[:, 0] + 0.5 * rows[:, 5] * rows[:, 8] + rng.normal(0, 0.2, 400) > 0.8
    samples.rows, samples.right = rows.tolist(), right.tolist()
    samples.kinds, samples.chairs = ["upright/same/winner"] * 400, ["c"] * 400

    calibrator = fit(samples)
    reference = GradientBoostingClassifier(**BOOSTING).fit(rows, right)
    fresh = rng.uniform(-0.5, 1.5, size=(200, len(SIGNALS)))
    for x in (rows, fresh):
        np.testing.assert_allclose(
            calibrator.probabilities(x), reference.predict_proba(x)[:, 1], atol=1e-12
        )
    assert len(calibrator.trees) == BOOSTING["n_estimators"]


@pytest.mark.slow
def test_a_tables_calibrator_ships_beside_the_general_one_and_reads_tables(
    tables_root: Path, tmp_path: Path
) -> None:
    """``--category table`` registers views of training tables; shipped in
    ``categories/table/confidence/``, it is the one the engine finds for tables."""
    if not (DEFAULT_MODEL_DIR / "model.safetensors").is_file():
        pytest.skip("model_store/ has no trained weights")
    out = tmp_path / "weights" / "categories" / "table" / "confidence"
    args = ["calibrate", "--out", str(out), "--views", "1", "--max-shapes", "2"]
    args += ["--pose-mode", "upright", "--category", "table", "--tables-dir", str(tables_root)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output

    card = find_category_calibrators(tmp_path / "weights")["table"].card
    assert card["command"].endswith("--category table")
    assert card["data"]["chairs"].startswith("2 training tables")
    assert set(card["data"]["chair_ids"]) <= set(SharedTables(tables_root).ids("train"))
