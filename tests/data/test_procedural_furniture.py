"""Tests for the procedural shelves and cabinets (closed parts, frame, sizes, seeds)."""

from __future__ import annotations

import numpy as np
import pytest

from catalign.data.procedural_furniture import (
    CABINET_STYLES,
    FURNITURE_KINDS,
    build_cabinet_parts,
    build_shelf_parts,
    generate_furniture,
    sample_cabinet_params,
    sample_shelf_params,
)

SEEDS = range(40)
# (width X, height Y, depth Z) ranges in metres, handles and overhangs included
SIZES = {
    "shelf": ((0.4, 1.25), (0.9, 2.0), (0.22, 0.47)),
    "cabinet": ((0.38, 1.86), (0.45, 2.0), (0.32, 0.7)),
}
BUILDERS = {
    "shelf": lambda seed: build_shelf_parts(sample_shelf_params(seed)),
    "cabinet": lambda seed: build_cabinet_parts(sample_cabinet_params(seed)),
}


@pytest.mark.parametrize("kind", FURNITURE_KINDS)
def test_parts_are_closed_and_the_mesh_is_watertight(kind: str) -> None:
    for seed in SEEDS:
        parts = BUILDERS[kind](seed)
        assert len(parts) >= 5, (kind, seed)
        for i, part in enumerate(parts):
            assert part.is_watertight, (kind, seed, i)
            assert part.is_winding_consistent, (kind, seed, i)
            assert part.volume > 0, (kind, seed, i)
        mesh = generate_furniture(kind, seed)
        assert mesh.is_watertight, (kind, seed)
        assert len(mesh.faces) == sum(len(p.faces) for p in parts) < 5000


@pytest.mark.parametrize("kind", FURNITURE_KINDS)
def test_plausible_sizes_standing_on_the_floor(kind: str) -> None:
    for seed in SEEDS:
        floor = np.vstack([p.vertices for p in BUILDERS[kind](seed)])
        assert floor[:, 1].min() == pytest.approx(0.0, abs=1e-9), (kind, seed)
        extents = np.ptp(floor, axis=0)
        for axis, (lo, hi) in enumerate(SIZES[kind]):
            assert lo <= extents[axis] <= hi, (kind, seed, axis, extents)
        centred = generate_furniture(kind, seed)
        np.testing.assert_allclose(centred.bounds.mean(axis=0), 0.0, atol=1e-9)
        np.testing.assert_allclose(centred.extents, extents, atol=1e-9)


@pytest.mark.parametrize("kind", FURNITURE_KINDS)
def test_deterministic_per_seed_and_different_across_seeds(kind: str) -> None:
    a, b = generate_furniture(kind, 3), generate_furniture(kind, 3)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    signatures = {
        (len(m.faces), *np.round(m.extents, 2))
        for m in (generate_furniture(kind, seed) for seed in SEEDS)
    }
    assert len(signatures) >= 38


def test_a_shelf_and_a_cabinet_of_one_seed_are_drawn_apart() -> None:
    shelf, cabinet = sample_shelf_params(7), sample_cabinet_params(7)
    assert shelf.width != cabinet.width and shelf.height != cabinet.height


def test_shelves_have_three_to_five_boards_some_open_backed() -> None:
    shelves = [sample_shelf_params(seed) for seed in SEEDS]
    assert all(3 <= s.boards <= 5 for s in shelves)
    backs = [s.back > 0 for s in shelves]
    assert 0 < sum(backs) < len(backs)


def test_every_cabinet_style_appears_and_its_front_faces_minus_z() -> None:
    cabinets = [sample_cabinet_params(seed) for seed in SEEDS]
    assert {c.style for c in cabinets} == set(CABINET_STYLES)
    for c in cabinets:
        floor = np.vstack([p.vertices for p in build_cabinet_parts(c)])
        assert floor[:, 2].max() == pytest.approx(0.5 * c.depth), c.seed  # a flat back
        if c.handle != "none":  # handles stand off the fronts, at -Z
            assert floor[:, 2].min() < -0.5 * c.depth - 0.02, c.seed


def test_an_unknown_kind_fails_loudly() -> None:
    with pytest.raises(ValueError, match="unknown furniture kind"):
        generate_furniture("lamp", 0)
