"""Training end to end on two procedural shapes: the loss falls, runs resume, exports load."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from catalign.data.shapes import procedural_shape
from catalign.errors import ConfigError
from catalign.features.resunet import build_model
from catalign.features.weights import CARD_FILE, WEIGHTS_FILE, load_model
from catalign.training.batches import pair_features
from catalign.training.config import TrainConfig
from catalign.training.loop import neighbours_within_categories, train
from catalign.training.loss import hardest_contrastive_loss
from catalign.training.pairs import PairSampler


@pytest.fixture(scope="module")
def two_shapes():
    return {s.shape_id: s for s in (procedural_shape(2), procedural_shape(11))}


def test_loss_falls_on_two_shapes(two_shapes) -> None:
    torch.manual_seed(0)
    ids = sorted(two_shapes)
    sampler = PairSampler(two_shapes, {ids[0]: [ids[1]], ids[1]: [ids[0]]}, voxel_size=0.04)
    rng = np.random.default_rng(0)
    samples = [sampler.sample(kind, i, rng) for kind in ("same", "cross") for i in ids]
    model = build_model("ResUNetSmall", conv1_kernel_size=3)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for step in range(25):
        generator = torch.Generator().manual_seed(step)
        terms = [
            hardest_contrastive_loss(
                fa,
                fb,
                torch.from_numpy(s.positives),
                torch.from_numpy(s.a.aligned).float(),
                torch.from_numpy(s.b.aligned).float(),
                s.neg_radius,
                generator,
            ).loss
            for s, (fa, fb) in zip(samples, pair_features(model, samples), strict=True)
        ]
        loss = torch.stack(terms).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5])


def _config(out: Path, **changes) -> TrainConfig:
    settings = {
        "model": "ResUNetSmall",
        "conv1_kernel_size": 3,
        "voxel_size": 0.05,
        "stage1_steps": 2,
        "stage2_steps": 2,
        "batch_size": 1,
        "validate_every": 2,
        "checkpoint_every": 1,
        "validation_pairs": 2,
        "out": out,
    }
    return TrainConfig(**(settings | changes))


def _log_steps(run: Path) -> list[int]:
    rows = csv.DictReader((run / "log.csv").read_text().splitlines())
    return [int(row["step"]) for row in rows]


def test_interrupted_training_resumes_and_exports_a_loadable_model(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("CATALIGN_CACHE_DIR", str(tmp_path / "cache"))
    shapes = {s.shape_id: s for s in (procedural_shape(k) for k in (2, 3, 11, 20))}
    config = _config(tmp_path / "run", checkpoint_every=2, validate_every=4)

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:  # killed in the validation of step 4
        patch.setattr("catalign.training.loop.validate", interrupt)
        with pytest.raises(KeyboardInterrupt):
            train(config, shapes, val_ids=["proc-0020"], progress=False)
    assert _log_steps(config.out) == [1, 2, 3]  # step 3 ran after the last checkpoint
    assert not (config.out / WEIGHTS_FILE).exists()

    with pytest.raises(ConfigError, match="other settings"):
        other = _config(config.out, checkpoint_every=2, validate_every=4, stage2_steps=3)
        train(other, shapes, val_ids=["proc-0020"], progress=False)

    card = train(config, shapes, val_ids=["proc-0020"], progress=False)
    assert _log_steps(config.out) == [1, 2, 3, 4]  # from step 2's checkpoint, step 3 once
    assert set(card["validation"]) == {"same_match_acc", "same_fmr", "cross_match_acc", "cross_fmr"}
    model, loaded_card = load_model(config.out)
    assert not model.training
    assert loaded_card["sha256"] == card["sha256"]
    assert loaded_card["training"]["stage1_steps"] == 2


def test_corrupt_weights_are_refused(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("CATALIGN_CACHE_DIR", str(tmp_path / "cache"))
    shapes = {s.shape_id: s for s in (procedural_shape(k) for k in (2, 3, 20))}
    config = _config(tmp_path / "run", stage1_steps=1, stage2_steps=0)
    train(config, shapes, val_ids=["proc-0020"], progress=False)
    weights = config.out / WEIGHTS_FILE
    weights.write_bytes(weights.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(ConfigError, match="does not match its card"):
        load_model(config.out)
    card = json.loads((config.out / CARD_FILE).read_text())
    assert card["architecture"]["name"] == "ResUNetSmall"


def test_cross_instance_neighbours_stay_within_a_category(tmp_path, monkeypatch) -> None:
    """Procedural shapes standing in for two categories: each shape's NCC neighbours are of
    its own category only, and the card counts the shapes of each."""
    monkeypatch.setenv("CATALIGN_CACHE_DIR", str(tmp_path / "cache"))
    shapes = {s.shape_id: s for s in (procedural_shape(k) for k in (2, 3, 11, 20, 21))}
    categories = {"proc-0002": "chair", "proc-0003": "chair", "proc-0020": "chair"}
    categories |= {"proc-0011": "table", "proc-0021": "table"}
    train_ids = sorted(set(shapes) - {"proc-0020"})
    near = neighbours_within_categories(shapes, train_ids, categories)
    for shape_id, found in near.items():
        assert found and all(categories[n] == categories[shape_id] for n, _ in found)
    config = _config(tmp_path / "run", stage1_steps=1, stage2_steps=1)
    card = train(config, shapes, val_ids=["proc-0020"], progress=False, categories=categories)
    assert card["categories"] == ["chair", "table"]
    assert card["training_data"]["categories"] == {"chair": 2, "table": 2}
