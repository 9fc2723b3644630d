from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

import catalign.data.neighbours as neighbours
from catalign.data.neighbours import (
    chamfer,
    emd_exact,
    emd_partitioned,
    ncc_samples,
    shape_neighbours,
)
from catalign.geometry.ncc import to_ncc
from catalign.geometry.sampling import sample_surface


def surface(mesh: trimesh.Trimesh, count: int, seed: int) -> np.ndarray:
    vertices, faces = np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces)
    return sample_surface(vertices, faces, count, np.random.default_rng(seed))


def box(extents) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents)


def bumpy_sphere(seed: int, amplitude: float = 0.05) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    radial = 1.0 + amplitude * np.random.default_rng(seed).standard_normal(len(sphere.vertices))
    return trimesh.Trimesh(sphere.vertices * radial[:, None], sphere.faces, process=False)


def brute_force_emd(a: np.ndarray, b: np.ndarray) -> float:
    cost = np.linalg.norm(a[:, None] - b[None], axis=2)
    rows = np.arange(len(a))
    return min(cost[rows, list(p)].mean() for p in itertools.permutations(range(len(b))))


@pytest.mark.parametrize("n", [5, 6])
@pytest.mark.parametrize("seed", range(4))
def test_emd_exact_matches_brute_force(n: int, seed: int):
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) + 0.3
    assert emd_exact(a, b) == pytest.approx(brute_force_emd(a, b), rel=1e-12)


def test_emd_exact_basic_properties(rng):
    a = rng.normal(size=(50, 3))
    assert emd_exact(a, a) == 0.0
    assert emd_exact(a, a[rng.permutation(50)]) == pytest.approx(0.0, abs=1e-12)
    b = rng.normal(size=(50, 3))
    assert emd_exact(a, b) == pytest.approx(emd_exact(b, a))
    # a pure translation of every point by d costs at most |d| (exactly |d| for a small shift)
    shift = np.array([0.0, 0.0, 0.01])
    assert emd_exact(a, a + shift) == pytest.approx(0.01)


def test_emd_exact_rejects_unequal_sizes():
    with pytest.raises(ValueError, match="equal-size"):
        emd_exact(np.zeros((5, 3)), np.zeros((6, 3)))


N = 1024


@pytest.fixture(scope="module")
def clouds() -> dict[str, np.ndarray]:
    """1024 NCC points of clearly different shapes."""
    meshes = {
        "sphere": trimesh.creation.icosphere(subdivisions=3),
        "bumpy": bumpy_sphere(3),
        "cube": box((1.0, 1.0, 1.0)),
        "rod": box((0.2, 0.2, 1.0)),
        "plate": box((1.0, 1.0, 0.1)),
    }
    return {name: to_ncc(surface(m, N, i)) for i, (name, m) in enumerate(meshes.items())}


@pytest.fixture(scope="module")
def exact(clouds) -> dict[tuple[str, str], float]:
    pairs = [("sphere", "bumpy"), ("sphere", "cube"), ("sphere", "rod"), ("sphere", "plate")]
    pairs += [("cube", "rod")]
    return {pair: emd_exact(clouds[pair[0]], clouds[pair[1]]) for pair in pairs}


@pytest.mark.parametrize(
    "pair", [("sphere", "rod"), ("sphere", "plate"), ("cube", "rod")], ids="-".join
)
def test_emd_partitioned_close_to_exact(clouds, exact, pair):
    """Within 15% on clearly different shapes. (The approximation adds the sampling noise of
    256-point chunks, about 0.02-0.03 in NCC, so near-identical shapes have a larger relative
    error; ``test_emd_partitioned_ranks_like_exact`` checks that the order survives that.)"""
    approx = emd_partitioned(clouds[pair[0]], clouds[pair[1]], 4, np.random.default_rng(0))
    assert approx == pytest.approx(exact[pair], rel=0.15)


def test_emd_partitioned_ranks_like_exact(clouds, exact):
    others = ["bumpy", "cube", "plate", "rod"]
    by_exact = sorted(others, key=lambda o: exact[("sphere", o)])
    rng = np.random.default_rng(0)
    approx = {o: emd_partitioned(clouds["sphere"], clouds[o], 4, rng) for o in others}
    assert sorted(others, key=approx.__getitem__) == by_exact
    assert by_exact[0] == "bumpy"  # the perturbed sphere is the nearest


def test_emd_partitioned_is_an_upper_bound(clouds):
    """The chunks' assignments together form one bijection of the full sets."""
    a, b = clouds["sphere"][:256], clouds["cube"][:256]
    full = emd_exact(a, b)
    for seed in range(3):
        assert emd_partitioned(a, b, 4, np.random.default_rng(seed)) >= full - 1e-12
    assert emd_partitioned(a, b, 1, np.random.default_rng(0)) == pytest.approx(full)


def test_emd_partitioned_unequal_sizes(clouds):
    a, b = clouds["sphere"][:1000], clouds["cube"][:900]
    value = emd_partitioned(a, b, 4, np.random.default_rng(0))
    assert 0.0 < value < 1.0


def test_chamfer():
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    assert chamfer(a, a) == 0.0
    assert chamfer(a, a + np.array([0, 0, 0.5])) == pytest.approx(0.5)
    assert chamfer(a, a[:1]) == pytest.approx(0.5 * (0.5 + 0.0))


def test_ncc_samples():
    points = np.random.default_rng(0).normal(size=(5000, 3)) * 10 + 3
    samples = ncc_samples(points, 512, seed=1)
    assert samples.shape == (512, 3)
    assert np.linalg.norm(np.ptp(samples, axis=0)) <= 1.0 + 1e-12
    np.testing.assert_array_equal(samples, ncc_samples(points, 512, seed=1))


# ---- shape_neighbours ------------------------------------------------------------------------

POINTS = 512
PARAMS = {"k": 3, "points": POINTS, "shortlist": 5, "parts": 2, "progress": False}


@pytest.fixture(scope="module")
def family() -> tuple[dict[str, np.ndarray], list[str]]:
    """Three families (bumpy spheres, boxes, rods) at different scales; train ids are the
    first three of each family, the fourth of each is a query only."""
    shapes: dict[str, np.ndarray] = {}
    for i in range(4):
        scale = 1.0 + 0.5 * i  # NCC removes scale
        shapes[f"sphere-{i}"] = surface(bumpy_sphere(10 + i), POINTS, i) * scale
        shapes[f"box-{i}"] = surface(box((1.0, 0.8 + 0.05 * i, 0.6)), POINTS, 10 + i) * scale
        shapes[f"rod-{i}"] = surface(box((0.15, 1.0, 0.15 + 0.02 * i)), POINTS, 20 + i) * scale
    train = [f"{f}-{i}" for f in ("sphere", "box", "rod") for i in range(3)]
    return shapes, train


@pytest.fixture(scope="module")
def computed(family, tmp_path_factory) -> tuple[Path, dict[str, list[tuple[str, float]]]]:
    shapes, train = family
    cache_dir = tmp_path_factory.mktemp("neighbours-cache")
    return cache_dir, shape_neighbours(shapes, train, cache_dir=cache_dir, **PARAMS)


def test_shape_neighbours(family, computed):
    shapes, train = family
    _, result = computed
    assert sorted(result) == sorted(shapes)
    for shape_id, found in result.items():
        ids = [n for n, _ in found]
        distances = [d for _, d in found]
        assert len(found) == 3
        assert shape_id not in ids
        assert set(ids) <= set(train)
        assert len(set(ids)) == 3
        assert distances == sorted(distances)
        assert all(d > 0 for d in distances)
        # the nearest shapes are the same kind (the rest of the family comes first)
        family_name = shape_id.split("-")[0]
        same_family = [i for i in train if i.startswith(family_name) and i != shape_id]
        assert set(ids[: len(same_family)]) == set(same_family), (shape_id, found)


def test_shape_neighbours_cache(family, computed, monkeypatch: pytest.MonkeyPatch):
    shapes, train = family
    cache_dir, first = computed
    files = list(cache_dir.glob("neighbours-*.json"))
    assert len(files) == 1
    assert not list(cache_dir.glob("*.tmp"))
    stored = json.loads(files[0].read_text())
    assert sorted(stored) == sorted(shapes)

    def no_recompute(*args, **kwargs):
        raise AssertionError("EMD recomputed although the result is cached")

    monkeypatch.setattr(neighbours, "emd_partitioned", no_recompute)
    monkeypatch.setattr(neighbours, "chamfer", no_recompute)
    second = shape_neighbours(shapes, train, cache_dir=cache_dir, **PARAMS)
    assert second == first
    assert all(isinstance(item, tuple) for found in second.values() for item in found)

    # other parameters are another cache entry: computed again (and here, refused)
    with pytest.raises(AssertionError, match="recomputed"):
        shape_neighbours(shapes, train, cache_dir=cache_dir, **(PARAMS | {"k": 2}))
    # so are the same ids with other points (a shape turned into another frame)
    turned = shapes | {"box-3": shapes["box-3"][:, [2, 1, 0]]}
    with pytest.raises(AssertionError, match="recomputed"):
        shape_neighbours(turned, train, cache_dir=cache_dir, **PARAMS)


def test_shape_neighbours_cache_dir_from_env(family, tmp_path, monkeypatch: pytest.MonkeyPatch):
    shapes, _ = family
    subset = {i: shapes[i] for i in ("sphere-0", "box-0", "rod-0", "rod-3")}
    monkeypatch.setenv("CATALIGN_CACHE_DIR", str(tmp_path / "cache"))
    result = shape_neighbours(subset, ["sphere-0", "box-0", "rod-0"], **(PARAMS | {"k": 2}))
    assert result["rod-3"][0][0] == "rod-0"
    assert len(result["rod-0"]) == 2  # only two other training shapes
    assert len(list((tmp_path / "cache").glob("neighbours-*.json"))) == 1
