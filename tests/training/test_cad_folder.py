"""``catalign train --data DIR``: a user's own CAD folder of a new category, trained from the
shipped weights, and the sentences that refuse a folder training cannot use."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from catalign.cli import app
from catalign.data.camera import camera_at
from catalign.data.procedural import generate_chair
from catalign.data.views import render_view, upright_rotation
from catalign.features.extractor import LearnedExtractor
from catalign.geometry.se3 import make_pose
from catalign.library.loaded import load
from catalign.paths import DEFAULT_MODEL_DIR
from catalign.registration.decision.confidence import Calibrator
from catalign.registration.engine import Engine
from catalign.training.cad_folder import cad_folders

runner = CliRunner()
BENCH_SEEDS = (5, 13, 14, 17)  # procedural seeds whose shape is a bench


@pytest.fixture(scope="module")
def benches(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder ``cad/bench/`` of four bench meshes, in centimetres as many CAD tools write."""
    root = tmp_path_factory.mktemp("cad")
    (root / "bench").mkdir()
    for seed in BENCH_SEEDS:
        mesh = generate_chair(seed)
        mesh.apply_scale(100.0)
        mesh.export(root / "bench" / f"bench_{seed}.ply")
    return root


def test_a_new_category_trains_from_the_shipped_weights(
    benches: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CATALIGN_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "run"
    arguments = ["train", "--data", str(benches), "--units", "cm", "--init-from"]
    arguments += [str(DEFAULT_MODEL_DIR), "--stage1-steps", "1", "--stage2-steps", "1"]
    result = runner.invoke(app, [*arguments, "--out", str(out)])
    assert result.exit_code == 0, result.output
    card = json.loads((out / "model_card.json").read_text())
    shipped = json.loads((DEFAULT_MODEL_DIR / "model_card.json").read_text())
    assert card["categories"] == ["bench", "chair"]  # the shipped weights had learnt chairs
    assert sum(card["training_data"]["categories"].values()) == len(BENCH_SEEDS) - 1
    assert card["training"]["model"] == shipped["training"]["model"]  # read from the card
    assert card["voxel_size"] == shipped["voxel_size"]
    # The shipped tables' own orientation networks and calibrator come along too.
    assert card["carried_from_init"] == ["orientation", "confidence", "categories"]
    assert (out / "categories" / "table" / "confidence" / "calibrator.json").is_file()

    # The same folder trains the benches' own orientation networks and calibrator, beside the
    # run's weights, where a query answered from benches alone finds them.
    own = out / "categories" / "bench"
    folder = ["--data", str(benches), "--units", "cm", "--category", "bench"]
    orientation = ["train-orientation", *folder, "--steps", "2", "--views-per-shape", "2"]
    orientation += ["--init-from", str(DEFAULT_MODEL_DIR / "orientation"), "--networks", "heading"]
    result = runner.invoke(app, [*orientation, "--out", str(own / "orientation")])
    assert result.exit_code == 0, result.output
    assert "model_store/categories/bench/orientation/" in result.output
    calibrate = ["calibrate", *folder, "--views", "1", "--pose-mode", "upright"]
    result = runner.invoke(
        app, [*calibrate, "--model-dir", str(out), "--out", str(own / "confidence")]
    )
    assert result.exit_code == 0, result.output
    oriented = json.loads((own / "orientation" / "orientation_card.json").read_text())
    assert oriented["training"]["category"] == "bench"
    assert oriented["training_data"]["train_benchs"] == len(BENCH_SEEDS) - 1

    # The run's folder serves at once: a library built with it answers a bench's view.
    library = tmp_path / "library"
    build = ["library", "build", str(benches), "--units", "cm", "--model-dir", str(out)]
    build += ["--workers", "1"]  # four models: worker processes would cost more than they save
    result = runner.invoke(app, [*build, "--out", str(library)])
    assert result.exit_code == 0, result.output
    extractor = LearnedExtractor(out)
    engine = Engine(extractor, load(library, extractor.fingerprint))
    shape = cad_folders(benches, None, units="cm")["bench"].metric("bench_13")
    pose = make_pose(upright_rotation(0.7), np.array([0.5, 0.2, 0.0]))
    camera = camera_at(np.array([0.5, 0.2, 0.3]), 1.8, 35.0, 20.0)
    points = render_view(shape, pose, camera, np.random.default_rng(1))
    answer = engine.register(points, up=np.array([0.0, 0.0, 1.0]), category="bench")
    assert answer.category == "bench" and answer.confidence is not None
    assert sorted(engine.orientations) == ["bench", "table"]
    benches_own = Calibrator.load(own / "confidence" / "calibrator.json")
    assert answer.confidence == pytest.approx(benches_own.probability(answer.evidence))


def test_the_folder_is_read_in_metres(benches: Path) -> None:
    folder = cad_folders(benches, None, units="cm")["bench"]
    heights = [folder.metric(i).height for i in folder.ids()]
    assert all(0.3 < h < 1.2 for h in heights), heights
    assert folder.ids("val") and folder.ids("train")


@pytest.mark.parametrize(
    ("arguments", "sentence"),
    [
        (["--category", "bench"], "no shared shapes of category 'bench'"),
        (["--data", "{loose}"], "outside a category sub-folder"),
        (["--data", "{benches}", "--category", "a", "--category", "b"], "got 2 categories"),
        (["--data", "{few}", "--category", "stool"], "training needs at least 3"),
        (["--data", "{benches}", "--category", "Bench"], "not a valid category"),
        (["--init-from", "{missing}"], "no such folder"),
    ],
)
def test_a_folder_training_cannot_use_is_one_sentence(
    benches: Path, tmp_path: Path, arguments: list[str], sentence: str
) -> None:
    loose = tmp_path / "loose"
    loose.mkdir()
    (loose / "a.ply").write_bytes((benches / "bench" / "bench_5.ply").read_bytes())
    few = tmp_path / "few"
    few.mkdir()
    (few / "a.ply").write_bytes((benches / "bench" / "bench_5.ply").read_bytes())
    places = {"loose": loose, "benches": benches, "few": few, "missing": tmp_path / "nowhere"}
    arguments = [a.format(**places) for a in arguments]
    out = tmp_path / "run"
    result = runner.invoke(app, ["train", *arguments, "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert sentence in result.output
    assert "Traceback" not in result.output
    assert not out.exists()
