"""Retrieval encoders: the anchor, the packing, the descriptors' invariances, a tiny training run
end to end, and the files a model folder ships them in."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from catalign.data.shapes import Shape, procedural_shape
from catalign.errors import ConfigError
from catalign.features.extractor import LearnedExtractor
from catalign.features.retrieval import (
    CARD_FILE,
    WEIGHTS_FILE,
    RetrievalHead,
    RetrievalModel,
    anchored,
    find_retrieval,
    load_retrieval,
    packed,
)
from catalign.training.config import RetrievalConfig
from catalign.training.retrieval import _hardest, run


def _cloud(seed: int, count: int = 300) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    features = rng.normal(size=(count, 32)).astype(np.float32)
    features /= np.linalg.norm(features, axis=1, keepdims=True)
    return rng.uniform(-0.3, 0.3, (count, 3)), features


def _head(seed: int = 0) -> RetrievalHead:
    torch.manual_seed(seed)
    return RetrievalHead(RetrievalModel(dims=16), {"sha256": "0" * 64, "penalty_weight": 0.5})


def test_the_anchor_is_the_middle_across_the_floor_and_the_lowest_point() -> None:
    points = np.array([[0.0, 0.2, 1.0], [1.0, 0.5, 3.0], [0.5, 1.0, 2.0]])
    assert np.allclose(anchored(points), points - [0.5, 0.2, 2.0])


def test_packing_subsamples_large_clouds_evenly_and_masks_small_ones() -> None:
    large, small = _cloud(0, 50), _cloud(1, 10)
    inputs, mask = packed([large, small], 20)
    assert inputs.shape == (2, 20, 35) and mask.sum(1).tolist() == [20, 10]
    kept = np.linspace(0, 49, 20).astype(int)
    assert np.allclose(inputs[0, :, 3:].numpy(), large[1][kept])
    assert not inputs[1, 10:].any()  # padding reads as nothing


def test_descriptors_are_unit_vectors_that_ignore_where_the_cloud_stands() -> None:
    head = _head()
    keypoints, features = _cloud(2)
    model = head.model_descriptor(keypoints, features)
    moved = head.model_descriptor(keypoints + np.array([3.0, -1.0, 2.0]), features)
    assert model.shape == (16,) and np.isclose(np.linalg.norm(model), 1.0, atol=1e-5)
    assert np.allclose(model, moved, atol=1e-5)
    views = head.view_descriptors([(keypoints, features), (keypoints[:100], features[:100])])
    assert views.shape == (2, 16) and np.allclose(np.linalg.norm(views, axis=1), 1.0, atol=1e-5)
    # the two encoders are different networks: a model and its own cloud as a view differ
    assert not np.allclose(views[0], model, atol=1e-3)


class _Procedural:
    """A shape source of procedural chairs: three to train on, two held out."""

    category = "chair"

    def ids(self, split: str | None = None) -> list[str]:
        return {
            "train": ["proc-0900", "proc-0901", "proc-0902"],
            "val": ["proc-0903", "proc-0904"],
        }[split or "train"]

    def metric(self, shape_id: str) -> Shape:
        return procedural_shape(int(shape_id.split("-")[1]))


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("retrieval")
    config = RetrievalConfig(
        steps=3, batch_size=3, negatives=2, procedural=2, views_per_shape=1, out=out
    )
    return out, run(config, [_Procedural()], LearnedExtractor(), progress=False)


@pytest.mark.slow
def test_a_training_run_writes_encoders_the_extractor_serves(trained, tmp_path: Path) -> None:
    out, card = trained
    assert json.loads((out / CARD_FILE).read_text()) == card
    assert card["data"]["shared_train_shapes"] == 3 and card["data"]["procedural_chairs"] == 2
    # 2 views of each of the 2 held-out chairs, among those and 2 unseen procedural chairs
    assert card["held_out"]["views"].startswith("2 of each of 2 validation shapes")
    assert 0.0 <= card["held_out"]["recall@1"] <= card["held_out"]["recall@10"] <= 1.0
    head = load_retrieval(out)
    assert head.penalty_weight == RetrievalConfig().penalty_weight
    keypoints, features = _cloud(3)
    assert head.model_descriptor(keypoints, features).shape == (RetrievalConfig().dims,)
    # a weights folder that ships them: the extractor's fingerprint names them
    folder = tmp_path / "weights"
    folder.mkdir()
    for name in ("model.safetensors", "model_card.json"):
        (folder / name).symlink_to(LearnedExtractor().model_dir / name)
    (folder / "retrieval").mkdir()
    for name in (CARD_FILE, WEIGHTS_FILE):
        (folder / "retrieval" / name).write_bytes((out / name).read_bytes())
    extractor = LearnedExtractor(folder)
    assert extractor.retrieval is not None
    assert extractor.fingerprint == f"{extractor.card['sha256']}+retrieval-{card['sha256'][:16]}"


def test_a_model_folder_without_retrieval_has_none(tmp_path: Path) -> None:
    assert find_retrieval(tmp_path) is None


@pytest.mark.slow
@pytest.mark.parametrize("missing", [CARD_FILE, WEIGHTS_FILE])
def test_half_of_a_shipped_head_is_refused(trained, tmp_path: Path, missing: str) -> None:
    out, _ = trained
    folder = tmp_path / "retrieval"
    folder.mkdir()
    for name in (CARD_FILE, WEIGHTS_FILE):
        if name != missing:
            (folder / name).write_bytes((out / name).read_bytes())
    with pytest.raises(ConfigError, match=f"expected {CARD_FILE} and {WEIGHTS_FILE}"):
        find_retrieval(tmp_path)


@pytest.mark.slow
def test_replaced_weights_are_refused(trained, tmp_path: Path) -> None:
    out, _ = trained
    for name in (CARD_FILE, WEIGHTS_FILE):
        (tmp_path / name).write_bytes((out / name).read_bytes())
    weights = tmp_path / WEIGHTS_FILE
    weights.write_bytes(weights.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(ConfigError, match="does not match its card"):
        load_retrieval(tmp_path)


def test_hard_negatives_are_the_nearest_models_other_than_the_steps_own() -> None:
    # 2 views, 6 models: view 0 is nearest models 5, 4, 3; view 1 models 1 (its own), 2, 3
    nearest = torch.tensor(
        [[0.9, 0.1, 0.2, 0.6, 0.7, 0.8], [0.1, 0.9, 0.8, 0.7, 0.2, 0.3]], dtype=torch.float32
    )
    positives = np.array([0, 1])
    hard = _hardest(nearest, positives, 1, np.random.default_rng(0))
    assert set(hard) <= {2, 3, 4, 5} and len(hard) == len(set(hard)) >= 1
    # with count 2 each view draws 2 of its 6 nearest others: at most every other model
    assert set(_hardest(nearest, positives, 2, np.random.default_rng(1))) <= {2, 3, 4, 5}


@pytest.mark.slow
def test_training_starts_from_given_encoders_and_names_them(trained, tmp_path: Path) -> None:
    parent_dir, parent = trained
    config = RetrievalConfig(
        steps=2, batch_size=3, negatives=2, procedural=2, views_per_shape=1,
        hard_negatives=1, mining_every=1, init_from=parent_dir, out=tmp_path / "child",
    )  # fmt: skip
    card = run(config, [_Procedural()], LearnedExtractor(), progress=False)
    assert card["started_from"] == parent["sha256"] != card["sha256"]
    assert f"--init-from {parent_dir}" in card["command"]
    assert "--hard-negatives 1" in card["command"]


@pytest.mark.slow
def test_encoders_over_other_features_are_refused_as_a_start(trained, tmp_path: Path) -> None:
    parent_dir, parent = trained
    folder = tmp_path / "foreign"
    folder.mkdir()
    (folder / WEIGHTS_FILE).write_bytes((parent_dir / WEIGHTS_FILE).read_bytes())
    (folder / CARD_FILE).write_text(json.dumps({**parent, "extractor": "0" * 64}))
    config = RetrievalConfig(steps=1, procedural=0, init_from=folder, out=tmp_path / "child")
    with pytest.raises(ConfigError, match="train from scratch"):
        run(config, [_Procedural()], LearnedExtractor(), progress=False)
