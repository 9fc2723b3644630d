from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from catalign.cli import app
from catalign.data.shapes import procedural_shape
from catalign.evaluation.protocol import build_cases, parse_views
from catalign.evaluation.report import COLUMNS
from catalign.evaluation.runner import given_up
from catalign.geometry.se3 import transform
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.config import EngineConfig
from catalign.registration.decision.confidence import SIGNALS, find_calibrator

runner = CliRunner()
# FPFH proposes no orientation and has no confidence: those columns are None.
PROPOSAL_COLUMNS = {"up@1", "up@3", "heading@1", "heading@2"}
CONFIDENCE_COLUMNS = {"ECE", "AUROC", "conf>=0.8 right", "conf>=0.8 share", "turns rescued"}
PERCENT_COLUMNS = [
    c for c in COLUMNS if not c.startswith("s/") and c not in PROPOSAL_COLUMNS | CONFIDENCE_COLUMNS
]


@pytest.fixture(scope="module")
def evaluated(chairs_root: Path, tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluate") / "r.json"
    args = ["evaluate", "--method", "fpfh", "--max-shapes", "2", "--views", "1"]
    result = runner.invoke(app, [*args, "--chairs-dir", str(chairs_root), "--out", str(out)])
    return result, out


def test_help_lists_evaluate():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    assert "evaluate" in result.output
    sub = runner.invoke(app, ["evaluate", "--help"])
    assert sub.exit_code == 0
    for option in ("--method", "--setting", "--views", "--max-shapes", "--floor", "--out"):
        assert option in sub.output


@pytest.mark.slow
def test_evaluate_end_to_end(evaluated):
    result, out = evaluated
    assert result.exit_code == 0, result.output
    assert "| fpfh | same | 2 |" in result.stdout
    assert "| fpfh | cross | 2 |" in result.stdout
    for column in COLUMNS:
        assert column in result.stdout
    assert f"report written to {out}" in result.stdout
    assert out.is_file()


@pytest.mark.slow
def test_evaluate_report_json(evaluated):
    result, out = evaluated
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert report["config"]["method"] == "fpfh"
    assert report["config"]["settings"] == ["same", "cross"]
    assert report["config"]["floor"] is False
    assert report["config"]["table"] is False
    assert report["split"] == {"val": 2, "train": 2}
    rows = {row["setting"]: row for row in report["rows"]}
    assert set(rows) == {"same", "cross"}
    for setting, row in rows.items():
        assert row["cases"] == 2
        for column in PERCENT_COLUMNS:
            value = row[column]
            if column == "top-1" and setting == "cross":
                assert value is None  # retrieval of the observed CAD is moot across instances
                continue
            assert value is not None and 0.0 <= value <= 100.0, (setting, column, value)
        assert all(row[column] is None for column in PROPOSAL_COLUMNS | CONFIDENCE_COLUMNS)
        assert row["refused"] == 0
        assert 0.0 < row["s/query median"] <= row["s/query p95"]
    assert set(report["cases"]) == {"same", "cross"}
    for cases in report["cases"].values():
        assert len(cases) == 2
        for case in cases:
            assert 0.0 <= case["rre_deg"] <= 180.0
            assert case["rte_m"] >= 0.0
            assert case["match_acc"] is None or 0.0 <= case["match_acc"] <= 1.0
    # in the same setting the library holds the observed shapes themselves
    val_ids = {case["case"].split("/")[0] for case in report["cases"]["same"]}
    assert {case["model_id"] for case in report["cases"]["same"]} <= val_ids


def test_unknown_method_exits_2(tmp_path: Path):
    # an empty chairs folder is enough: the method is checked before any shape is loaded
    out = tmp_path / "x.json"
    result = runner.invoke(
        app, ["evaluate", "--method", "nope", "--chairs-dir", str(tmp_path), "--out", str(out)]
    )
    assert result.exit_code == 2
    assert "unknown method 'nope'" in result.stderr
    assert "known methods: fpfh" in result.stderr
    assert "Traceback" not in result.output
    assert not out.exists()


def test_unknown_setting_exits_2(tmp_path: Path):
    result = runner.invoke(
        app, ["evaluate", "--setting", "bogus", "--chairs-dir", str(tmp_path / "none")]
    )
    assert result.exit_code == 2
    assert "unknown setting 'bogus'" in result.stderr
    assert "same or cross" in result.stderr


def test_unknown_pose_mode_exits_2(tmp_path: Path):
    args = ["evaluate", "--pose-mode", "sideways", "--chairs-dir", str(tmp_path)]
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert "unknown pose mode 'sideways'" in result.stderr


@pytest.mark.slow
def test_evaluate_with_floor_records_it(chairs_root: Path, tmp_path: Path):
    out = tmp_path / "floor.json"
    args = ["evaluate", "--floor", "--max-shapes", "1", "--views", "1", "--setting", "same"]
    result = runner.invoke(app, [*args, "--chairs-dir", str(chairs_root), "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert report["config"]["floor"] is True
    assert report["config"]["pose_mode"] == "upright"
    assert [row["cases"] for row in report["rows"]] == [1]


@pytest.mark.slow
def test_evaluate_on_tables_scores_to_the_nearest_symmetric_pose(tables_root: Path, tmp_path):
    out = tmp_path / "tables.json"
    args = ["evaluate", "--method", "learned", "--category", "table", "--max-shapes", "3"]
    args += ["--views", "1", "--setting", "same", "--tables-dir", str(tables_root)]
    result = runner.invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert report["config"]["category"] == "table"
    (row,) = report["rows"]
    assert row["cases"] == 3 and row["RRE<10"] >= 0
    # Each case's error is the smallest over the observed table's equivalent poses.
    assert all(case["rre_deg"] <= 180.0 for case in report["cases"]["same"])


def test_an_unknown_category_or_a_missing_tables_folder_exits_2(tmp_path: Path):
    unknown = runner.invoke(app, ["evaluate", "--category", "sofa"])
    assert unknown.exit_code == 2 and "unknown category 'sofa'" in unknown.stderr
    args = ["evaluate", "--category", "table", "--tables-dir", str(tmp_path / "none")]
    missing = runner.invoke(app, args)
    assert missing.exit_code == 2 and "CATALIGN_TABLES_DIR" in missing.stderr


def test_build_cases_with_floor():
    shapes = {"p3": procedural_shape(3)}
    plain = build_cases(shapes, views=2, seed=5)
    kept = build_cases(shapes, views=2, seed=5, floor=True)
    for a, b in zip(plain, kept, strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)  # the same placements and cameras ...
        posed = transform(shapes["p3"].mesh.vertices, b.pose)
        low, high = posed[:, :2].min(axis=0), posed[:, :2].max(axis=0)
        beyond = ((b.points[:, :2] < low - 0.05) | (b.points[:, :2] > high + 0.05)).any(axis=1)
        near_floor = np.abs(b.points[:, 2] - posed[:, 2].min()) < 0.03
        assert (beyond & near_floor).sum() > 1000  # ... plus floor around the chair
        beyond = ((a.points[:, :2] < low - 0.05) | (a.points[:, :2] > high + 0.05)).any(axis=1)
        assert beyond.sum() == 0


def test_build_cases_under_a_table_are_their_plain_twins_less_what_the_table_hides():
    shapes = {"p3": procedural_shape(3)}
    plain = build_cases(shapes, views=3, seed=5)
    tabled = build_cases(shapes, views=3, seed=5, table=True)
    for a, b in zip(plain, tabled, strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)
        assert len(b.points) < len(a.points)
        seen = {tuple(p) for p in a.points}
        assert all(tuple(p) in seen for p in b.points)


@pytest.mark.parametrize(
    ("pose_mode", "floor"), [("turned", False), ("turned", True), ("so3", True)]
)
def test_turned_views_are_the_upright_ones_turned_at_random(pose_mode: str, floor: bool):
    shapes = {"p3": procedural_shape(3)}
    upright = build_cases(shapes, views=2, seed=5, floor=floor)
    turned = build_cases(shapes, views=2, seed=5, pose_mode=pose_mode, floor=floor)
    tilts = []
    for a, b in zip(upright, turned, strict=True):
        turn = b.pose @ np.linalg.inv(a.pose)  # the scene's turn, about the world origin
        np.testing.assert_allclose(turn[:3, 3], 0.0, atol=1e-9)
        np.testing.assert_allclose(transform(a.points, turn), b.points, atol=1e-9)
        tilts.append(np.degrees(np.arccos(np.clip(turn[2, 2], -1.0, 1.0))))
    assert max(tilts) > 20.0  # really turned, not upright
    for a, b in zip(upright, turned, strict=True):  # the camera turned with the scene
        assert b.elevation_deg == pytest.approx(a.elevation_deg)


def test_the_camera_looks_down_on_upright_chairs_and_from_anywhere_on_turned_ones():
    shapes = {f"p{seed}": procedural_shape(seed) for seed in (3, 4, 5)}
    upright = [c.elevation_deg for c in build_cases(shapes, views=4, seed=1)]
    turned = [c.elevation_deg for c in build_cases(shapes, views=4, seed=1, pose_mode="so3")]
    assert min(upright) >= 5.0 and max(upright) <= 50.0  # the camera's range over the floor
    assert min(turned) < 0.0 < max(turned)  # some turned chairs are seen from below


def test_unknown_pose_mode_exits_2_with_the_modes(chairs_root: Path):
    result = runner.invoke(
        app, ["evaluate", "--pose-mode", "tilted", "--chairs-dir", str(chairs_root)]
    )
    assert result.exit_code == 2
    assert "upright, so3 or turned" in result.stderr


def test_missing_chairs_folder_exits_2(tmp_path: Path):
    result = runner.invoke(app, ["evaluate", "--chairs-dir", str(tmp_path / "none")])
    assert result.exit_code == 2
    assert "CATALIGN_CHAIRS_DIR" in result.stderr


def test_views_must_be_positive():
    result = runner.invoke(app, ["evaluate", "--views", "0"])
    assert result.exit_code == 2  # click's own usage error


def test_engine_options_are_refused_for_the_classic_baseline(tmp_path: Path):
    out = tmp_path / "r.json"
    result = runner.invoke(
        app, ["evaluate", "--method", "fpfh", "--engine", "top_k=3", "--out", str(out)]
    )
    assert result.exit_code == 2
    assert "--engine options apply to learned and fpfh-engine" in result.output
    assert not out.exists()


@pytest.mark.slow
def test_engine_options_reach_the_engine_and_the_report(chairs_root: Path, tmp_path: Path):
    out = tmp_path / "engine.json"
    args = ["evaluate", "--method", "learned", "--max-shapes", "2", "--views", "1"]
    args += ["--setting", "same", "--engine", "top_k=1", "--engine", "decision.alternatives=0"]
    result = runner.invoke(app, [*args, "--chairs-dir", str(chairs_root), "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    engine = report["config"]["engine"]
    assert (engine["top_k"], engine["decision"]["alternatives"]) == (1, 0)
    assert engine["match"]["query_points"] == EngineConfig().match.query_points
    cases = report["cases"]["same"]
    assert len(cases) == 2
    assert all(case.get("alternatives", []) == [] for case in cases)  # alternatives=0 reached it
    # Each answer keeps its confidence signals: the shipped calibrator reads its confidence
    # from them again, so another calibrator can be scored on the same answers.
    calibrator = find_calibrator(DEFAULT_MODEL_DIR)
    assert calibrator is not None
    for case in cases:
        row = np.array([[case["evidence"][name] for name in SIGNALS]])
        assert calibrator.probabilities(row)[0] == pytest.approx(case["confidence"])


def test_an_up_error_needs_an_up_to_tilt():
    result = runner.invoke(app, ["evaluate", "--pose-mode", "so3", "--up-error", "5"])
    assert result.exit_code == 2
    assert "--up-error tilts the up the method is told: it needs --up-prior" in result.output


def test_the_up_told_is_tilted_by_the_up_error():
    for error in (0.0, 5.0, 10.0):
        up = given_up(error)
        assert np.isclose(np.linalg.norm(up), 1.0)
        assert np.isclose(np.degrees(np.arccos(up @ np.array([0.0, 0.0, 1.0]))), error, atol=1e-6)


@pytest.mark.parametrize(
    ("text", "parsed"),
    [
        ("4", ("single", 4)),
        ("single", ("single", 2)),
        ("fused", ("fused", 2)),
        ("fused:3", ("fused", 3)),
    ],
)
def test_views_name_their_source_and_count(text: str, parsed: tuple[str, int]):
    assert parse_views(text) == parsed


@pytest.mark.parametrize("text", ["0", "fused:0", "fused:x", "depth", "single:-1"])
def test_views_the_evaluation_cannot_make_exit_2_with_what_it_takes(text: str):
    result = runner.invoke(app, ["evaluate", "--views", text])
    assert result.exit_code == 2
    assert "--views" in result.stderr and (
        "single, fused" in result.stderr or ">= 1" in result.stderr
    )


def test_fused_cases_are_reconstructions_of_the_standing_shape_and_turn_like_single_ones():
    shapes = {"p3": procedural_shape(3)}
    fused = build_cases(shapes, views=2, seed=5, source="fused")
    again = build_cases(shapes, views=2, seed=5, source="fused")
    single = build_cases(shapes, views=2, seed=5)
    for case, twin, one in zip(fused, again, single, strict=True):
        np.testing.assert_array_equal(case.points, twin.points)  # the seed fixes everything
        np.testing.assert_allclose(case.pose[:3, :3] @ [0, 1, 0], [0, 0, 1], atol=1e-9)
        posed = transform(shapes["p3"].points, case.pose)
        on_chair = cKDTree(posed).query(case.points)[0] < 0.03
        assert on_chair.mean() > 0.5
        # A reconstruction covers more of the chair than one depth frame does.
        covered = cKDTree(case.points).query(posed)[0] < 0.02
        seen_once = cKDTree(one.points).query(posed)[0] < 0.02
        assert covered.mean() > seen_once.mean()
    turned = build_cases(shapes, views=2, seed=5, source="fused", pose_mode="so3")
    for case, upright in zip(turned, fused, strict=True):
        turn = case.pose @ np.linalg.inv(upright.pose)
        np.testing.assert_allclose(transform(upright.points, turn), case.points, atol=1e-9)


@pytest.mark.slow
def test_evaluate_on_fused_views_records_the_source(chairs_root: Path, tmp_path: Path):
    out = tmp_path / "fused.json"
    args = ["evaluate", "--views", "fused:1", "--max-shapes", "1", "--setting", "same"]
    result = runner.invoke(app, [*args, "--chairs-dir", str(chairs_root), "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert report["config"]["source"] == "fused" and report["config"]["views"] == 1
    assert [row["cases"] for row in report["rows"]] == [1]
