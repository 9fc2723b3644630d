"""Orientation proposals: the occupancy grid, peak picking, and a tiny training run end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from catalign.data.shapes import Shape, procedural_shape
from catalign.errors import ConfigError
from catalign.features.orientation import (
    CARD_FILE,
    GRID,
    HEADING_ANGLES,
    HEADING_BINS,
    UP_DIRECTIONS,
    WEIGHTS_FILE,
    fibonacci_sphere,
    find_category_orientations,
    find_orientation,
    load_orientation,
    occupancy_grids,
    peaks,
    principal_frames,
)
from catalign.geometry.sampling import voxel_downsample
from catalign.geometry.se3 import random_rotation
from catalign.training.orientation import (
    OrientationConfig,
    ViewSet,
    heading_labels,
    render_views,
    soft_labels,
    train_orientation,
)


def test_fibonacci_sphere_is_even() -> None:
    directions = fibonacci_sphere(256)
    assert np.allclose(np.linalg.norm(directions, axis=1), 1.0)
    # Every direction of the sphere has a bin within 10 degrees (bins are about 13 apart).
    probes = np.random.default_rng(0).normal(size=(2000, 3))
    probes /= np.linalg.norm(probes, axis=1, keepdims=True)
    nearest = np.degrees(np.arccos(np.clip((probes @ directions.T).max(axis=1), -1, 1)))
    assert nearest.max() < 10.0
    assert abs(directions.mean(axis=0)).max() < 0.01


def test_occupancy_grid_ignores_density_and_place() -> None:
    rng = np.random.default_rng(0)
    cube = rng.uniform(-0.4, 0.4, size=(3000, 3))
    far = cube + np.array([5.0, -2.0, 1.0])
    grids = occupancy_grids([cube, np.repeat(cube, 4, axis=0), far])
    assert grids.shape == (3, 1, GRID, GRID, GRID)
    assert set(np.unique(grids.numpy())) == {0.0, 1.0}
    assert bool((grids[0] == grids[1]).all())  # repeated points change nothing
    # The same cube elsewhere: the same cells (up to rounding at cell borders).
    overlap = (grids[0] * grids[2]).sum() / grids[2].sum()
    assert overlap > 0.99


def test_peaks_are_distinct_and_refined() -> None:
    truth = [np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])]
    probabilities = 0.7 * soft_labels(truth[0][None], UP_DIRECTIONS, 8.0)[0]
    probabilities += 0.3 * soft_labels(truth[1][None], UP_DIRECTIONS, 8.0)[0]
    found = peaks(probabilities, UP_DIRECTIONS, 3, distinct_deg=30.0)
    assert len(found) == 3
    for (direction, _), expected in zip(found[:2], truth, strict=False):
        assert np.degrees(np.arccos(direction @ expected)) < 4.0
        assert np.isclose(np.linalg.norm(direction), 1.0)
    assert found[0][1] > found[1][1] > found[2][1]
    angle = np.degrees(np.arccos(np.clip(found[2][0] @ found[0][0], -1, 1)))
    assert angle > 20.0  # not the first peak again (its best bin is beyond 30 degrees)


def test_principal_frames_are_the_four_signings_of_the_principal_axes() -> None:
    rng = np.random.default_rng(0)
    turn = random_rotation(rng)
    points = (rng.normal(size=(4000, 3)) * [0.5, 0.2, 0.05]) @ turn.T + [3.0, -1.0, 2.0]
    frames = principal_frames(points)
    assert frames.shape == (4, 3, 3)
    for frame in frames:
        assert np.allclose(frame.T @ frame, np.eye(3)) and np.isclose(np.linalg.det(frame), 1.0)
        spread = np.cov((points @ frame).T)
        assert np.allclose(spread, np.diag(np.diag(spread)), atol=1e-3)
        assert spread[0, 0] > spread[1, 1] > spread[2, 2]
        # The widest axis is the one the cloud was stretched along, up to its sign.
        assert abs(frame[:, 0] @ turn[:, 0]) > 0.99
    signs = np.sign(np.einsum("kij,ij->kj", frames, frames[0]))
    assert sorted(map(tuple, signs)) == sorted([(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)])


@pytest.mark.parametrize("up_frame", ["view", "principal"])
def test_a_tiny_training_run_ships_a_working_proposer(tmp_path: Path, up_frame: str) -> None:
    shapes = [procedural_shape(seed) for seed in (0, 1)]
    views = render_views(
        shapes, 3, seed=0, view_points=256, so3_share=0.5, floor_share=0.5, progress=False
    )
    assert views.points.shape == (6, 256, 3)
    config = OrientationConfig(
        steps=3, batch_size=4, min_points=64, up_frame=up_frame, out=tmp_path / "run"
    )
    card = train_orientation(config, views, held_out=views, progress=False)

    assert (tmp_path / "run" / WEIGHTS_FILE).is_file()
    stored = json.loads((tmp_path / "run" / CARD_FILE).read_text())
    assert stored["sha256"] == card["sha256"]
    assert stored["training"]["steps"] == 3
    assert stored["architecture"]["up_frame"] == up_frame
    assert f"--up-frame {up_frame}" in stored["command"] or up_frame == "view"
    assert set(stored["held_out_accuracy"]) == {
        "up_top1",
        "up_top3",
        "heading_top1",
        "heading_top2",
    }

    proposer = load_orientation(tmp_path / "run")
    points = views.points[0].astype(np.float64) @ random_rotation(np.random.default_rng(1)).T
    ups = proposer.ups(points, 3)
    assert len(ups) == 3
    assert all(np.isclose(np.linalg.norm(p.value), 1.0) for p in ups)
    # Each score is the probability mass of its own peak (an untrained net's are near even).
    assert all(p.score > 0 for p in ups) and sum(p.score for p in ups) <= 1.0 + 1e-9
    headings = proposer.headings([points, points[:100]], 2)
    assert [len(h) for h in headings] == [2, 2]
    assert all(-np.pi <= p.value <= np.pi for h in headings for p in h)


def test_fused_views_see_more_of_the_chair_than_single_ones() -> None:
    """A fused view is a reconstruction of the placed chair from a camera trajectory: it spans
    more of the chair than one camera does, at the same pose."""
    shapes = [procedural_shape(0)]
    options = {"view_points": 4096, "so3_share": 0.0, "floor_share": 0.0, "progress": False}
    single = render_views(shapes, 6, seed=3, **options)
    fused = render_views(shapes, 6, seed=3, fused_share=1.0, **options)
    unchanged = render_views(shapes, 6, seed=3, fused_share=0.0, **options)

    np.testing.assert_array_equal(unchanged.points, single.points)
    np.testing.assert_array_equal(fused.rotations, single.rotations)
    cells = [
        [len(voxel_downsample(v.points[i].astype(np.float64), 0.05)[0]) for i in range(6)]
        for v in (single, fused)
    ]
    assert (np.array(cells[1]) > np.array(cells[0])).all(), cells
    config = OrientationConfig(fused_share=0.3)
    assert "--fused-share 0.3" in config.command()


def test_the_card_command_renders_as_many_views_in_any_rotation() -> None:
    assert "--so3-share 0.8" in OrientationConfig(so3_share=0.8).command()
    assert "--so3-share" not in OrientationConfig().command()


def _one_step_run(folder: Path, **options: object) -> None:
    """A proposer trained for one step on two views of a procedural chair, in ``folder``."""
    views = render_views(
        [procedural_shape(0)],
        2,
        seed=0,
        view_points=128,
        so3_share=0.0,
        floor_share=0.0,
        progress=False,
    )
    config = OrientationConfig(steps=1, batch_size=2, min_points=64, out=folder, **options)
    train_orientation(config, views, progress=False)


def test_a_replaced_weights_file_is_refused(tmp_path: Path) -> None:
    _one_step_run(tmp_path)
    weights = tmp_path / WEIGHTS_FILE
    weights.write_bytes(weights.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(ConfigError, match="does not match its card"):
        load_orientation(tmp_path)


def test_a_model_folder_without_orientation_has_no_proposer(tmp_path: Path) -> None:
    assert find_orientation(tmp_path) is None


@pytest.mark.parametrize("missing", [CARD_FILE, WEIGHTS_FILE])
def test_half_a_shipped_proposer_is_refused_not_ignored(tmp_path: Path, missing: str) -> None:
    _one_step_run(tmp_path / "orientation")
    assert find_orientation(tmp_path) is not None
    (tmp_path / "orientation" / missing).unlink()
    with pytest.raises(ConfigError, match=f"expected {CARD_FILE} and {WEIGHTS_FILE}"):
        find_orientation(tmp_path)


def test_a_run_of_one_network_keeps_the_other_as_it_was(tmp_path: Path) -> None:
    _one_step_run(tmp_path / "first")
    _one_step_run(
        tmp_path / "up", networks="up", init_from=tmp_path / "first", up_frame="principal"
    )
    first = load_orientation(tmp_path / "first").model
    second = load_orientation(tmp_path / "up").model
    assert second.up_frame == "principal"
    kept = first.heading.state_dict()
    assert all(torch.equal(kept[k], v) for k, v in second.heading.state_dict().items())
    moved = first.up.state_dict()
    assert not all(torch.equal(moved[k], v) for k, v in second.up.state_dict().items())
    with pytest.raises(ValueError, match="the other needs init_from"):
        OrientationConfig(networks="heading")


def test_a_wider_up_network_starts_afresh_beside_the_kept_heading_network(
    tmp_path: Path,
) -> None:
    _one_step_run(tmp_path / "first")
    _one_step_run(tmp_path / "wide", networks="up", init_from=tmp_path / "first", up_width=8)
    first = load_orientation(tmp_path / "first").model
    wide = load_orientation(tmp_path / "wide")
    assert wide.card["architecture"]["up_width"] == 8
    assert "--up-width 8" in wide.card["command"]
    assert wide.model.up.config["width"] == 8 and wide.model.heading.config["width"] == 16
    kept = first.heading.state_dict()
    assert all(torch.equal(kept[k], v) for k, v in wide.model.heading.state_dict().items())
    assert len(wide.ups(np.random.default_rng(0).normal(size=(400, 3)), 3)) == 3
    # The heading network cannot be kept from a run whose heading network has another width.
    with pytest.raises(ConfigError, match="heading network is kept from init_from"):
        _one_step_run(tmp_path / "bad", networks="up", init_from=tmp_path / "first", width=8)


def test_a_symmetric_shapes_heading_label_holds_every_equivalent_heading() -> None:
    """A table that looks the same turned half way round is as right either way: its label
    peaks at both headings; a round one is labelled uniformly; a chair at its one heading."""
    heading = HEADING_ANGLES[3]
    labels = heading_labels(np.full(4, heading), np.array([1, 2, 4, 0]), 10.0)

    assert np.allclose(labels.sum(axis=1), 1.0)
    plain = soft_labels(np.array([[np.cos(heading), np.sin(heading)]]), _circle(), 10.0)[0]
    np.testing.assert_allclose(labels[0], plain)
    half = HEADING_BINS // 2
    for row, order in ((1, 2), (2, 4)):
        step = HEADING_BINS // order
        peaks_at = sorted(np.argsort(labels[row])[-order:].tolist())
        assert peaks_at == sorted((3 + k * step) % HEADING_BINS for k in range(order))
    assert labels[1][3] == pytest.approx(labels[1][3 + half])
    np.testing.assert_allclose(labels[3], 1.0 / HEADING_BINS)


def test_views_keep_the_symmetry_of_their_shape_and_old_caches_read_as_asymmetric(
    tmp_path: Path,
) -> None:
    shapes = [procedural_shape(0), _square_box()]
    views = render_views(
        shapes, 2, seed=0, view_points=128, so3_share=0.0, floor_share=0.0, progress=False
    )
    assert views.orders.tolist() == [1, 1, 4, 4]
    views.save(tmp_path / "views.npz")
    np.testing.assert_array_equal(ViewSet.load(tmp_path / "views.npz").orders, views.orders)
    np.savez(
        tmp_path / "old.npz", points=views.points, counts=views.counts, rotations=views.rotations
    )
    assert ViewSet.load(tmp_path / "old.npz").orders.tolist() == [1, 1, 1, 1]


def test_a_categorys_own_proposer_is_found_beside_the_general_one(tmp_path: Path) -> None:
    assert find_category_orientations(tmp_path) == {}
    _one_step_run(tmp_path / "orientation")
    _one_step_run(tmp_path / "categories" / "table" / "orientation")
    (tmp_path / "categories" / "bench").mkdir()  # a category with nothing of its own

    found = find_category_orientations(tmp_path)
    assert list(found) == ["table"]
    card = json.loads((tmp_path / "categories" / "table" / "orientation" / CARD_FILE).read_text())
    assert found["table"].card["sha256"] == card["sha256"]


def _circle() -> np.ndarray:
    return np.stack([np.cos(HEADING_ANGLES), np.sin(HEADING_ANGLES)], axis=1)


def _square_box() -> Shape:
    """A box 0.8 m square and 0.5 m tall (+Y up), sampled on its surface: a quarter turn maps
    it onto itself."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, size=(6000, 3))
    axis = rng.integers(0, 3, len(points))
    points[np.arange(len(points)), axis] = rng.choice([-1.0, 1.0], len(points))
    return Shape(shape_id="box", points=points * np.array([0.4, 0.25, 0.4]) + [0, 0.25, 0])
