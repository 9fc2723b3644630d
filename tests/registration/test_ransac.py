from __future__ import annotations

import time

import numpy as np
import pytest

from catalign.errors import DegenerateInputError, InvalidInputError
from catalign.geometry.rigid_fit import kabsch, kabsch_batch, umeyama, umeyama_batch
from catalign.geometry.se3 import (
    axis_angle,
    make_pose,
    random_rotation,
    rotation_error_deg,
    transform,
    translation_error,
)
from catalign.registration.baseline import open3d_recipe
from catalign.registration.baseline.open3d_recipe import point_cloud
from catalign.registration.stages.ransac import SCALE_RANGE, count_inliers, ransac, residual_terms

X = np.array([1.0, 0.0, 0.0])
Y = np.array([0.0, 1.0, 0.0])
Z = np.array([0.0, 0.0, 1.0])
INLIER_DISTANCE = 0.03  # metres; correspondence noise is 3 mm
CHAIR_BOX = np.array([0.5, 0.9, 0.5])  # extents of a chair, +Y up


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return make_pose(random_rotation(rng), rng.uniform(-1.0, 1.0, size=3))


def correspondences(
    rng: np.random.Generator, n: int, outlier_ratio: float, pose: np.ndarray, noise: float = 0.003
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Model points, matched observation points and the inlier mask; outliers are uniform in
    the observation's bounding box."""
    src = (rng.random((n, 3)) - 0.5) * CHAIR_BOX
    dst = transform(src, pose) + rng.normal(scale=noise, size=(n, 3))
    outliers = rng.permutation(n)[: round(outlier_ratio * n)]
    dst[outliers] = rng.uniform(dst.min(axis=0), dst.max(axis=0), size=(len(outliers), 3))
    inliers = np.ones(n, dtype=bool)
    inliers[outliers] = False
    return src, dst, inliers


def assert_pose_close(found: np.ndarray, pose: np.ndarray, deg: float = 1.0, metres: float = 0.01):
    assert rotation_error_deg(found[:3, :3], pose[:3, :3]) < deg
    assert translation_error(found[:3, 3], pose[:3, 3]) < metres


# --- Kabsch and Umeyama ---------------------------------------------------------------------


def test_kabsch_batch_recovers_rotations_exactly_and_matches_single_version(rng):
    rotations = np.stack([random_rotation(rng) for _ in range(50)])
    translations = rng.normal(size=(50, 3))
    src = rng.normal(size=(50, 6, 3))
    dst = np.einsum("hij,hkj->hki", rotations, src) + translations[:, None]
    found_r, found_t = kabsch_batch(src, dst)
    np.testing.assert_allclose(found_r, rotations, atol=1e-10)
    np.testing.assert_allclose(found_t, translations, atol=1e-10)
    for h in range(50):
        single_r, single_t = kabsch(src[h], dst[h])
        np.testing.assert_allclose(single_r, found_r[h], atol=1e-12)
        np.testing.assert_allclose(single_t, found_t[h], atol=1e-12)


def test_kabsch_of_three_points_is_exact(rng):
    """Three points span a plane: the covariance has rank 2, and without the reflection fix the
    SVD may return a mirror image half of the time."""
    rotations = np.stack([random_rotation(rng) for _ in range(200)])
    src = rng.normal(size=(200, 3, 3))
    dst = np.einsum("hij,hkj->hki", rotations, src)
    found, _ = kabsch_batch(src, dst)
    np.testing.assert_allclose(found, rotations, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(found), 1.0)


def test_kabsch_returns_a_rotation_for_mirrored_points(rng):
    src = rng.normal(size=(20, 3))
    mirrored = src * np.array([-1.0, 1.0, 1.0])
    rotation, _ = kabsch(src, mirrored)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    rotations, _ = kabsch_batch(np.stack([src, src]), np.stack([mirrored, src]))
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0)


def test_umeyama_recovers_a_known_scale(rng):
    rotation, translation = random_rotation(rng), rng.normal(size=3)
    src = rng.normal(size=(30, 3))
    dst = 2.5 * src @ rotation.T + translation
    scale, found_r, found_t = umeyama(src, dst)
    assert scale == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(found_r, rotation, atol=1e-10)
    np.testing.assert_allclose(found_t, translation, atol=1e-10)
    scales, _, _ = umeyama_batch(np.stack([src, src]), np.stack([dst, src]))
    np.testing.assert_allclose(scales, [2.5, 1.0])
    assert umeyama(src, dst, estimate_scale=False)[0] == 1.0


def test_weighted_kabsch_ignores_zero_weight_points(rng):
    rotation, translation = random_rotation(rng), rng.normal(size=3)
    src = rng.normal(size=(30, 3))
    dst = src @ rotation.T + translation
    dst[:10] = rng.normal(size=(10, 3))
    weights = np.r_[np.zeros(10), rng.uniform(0.5, 2.0, size=20)]
    found_r, found_t = kabsch(src, dst, weights)
    np.testing.assert_allclose(found_r, rotation, atol=1e-10)
    np.testing.assert_allclose(found_t, translation, atol=1e-10)
    with pytest.raises(InvalidInputError, match="weights"):
        kabsch(src, dst, np.zeros(30))


def test_batched_inlier_count_matches_brute_force(rng):
    x, y = rng.normal(size=(300, 3)), rng.normal(size=(300, 3))
    scale, rotation, translation = umeyama_batch(
        rng.normal(size=(40, 3, 3)), rng.normal(size=(40, 3, 3))
    )
    predicted = scale[:, None, None] * np.einsum("hij,nj->hni", rotation, x) + translation[:, None]
    expected = (np.linalg.norm(predicted - y, axis=2) < 1.0).sum(axis=1)
    counts = count_inliers(residual_terms(x, y), scale, rotation, translation, 1.0)
    np.testing.assert_array_equal(counts, expected)


# --- RANSAC -------------------------------------------------------------------------------


@pytest.mark.parametrize("outlier_ratio", [0.7, 0.9])
def test_ransac_recovers_a_rigid_pose_among_outliers(rng, outlier_ratio: float):
    pose = random_pose(rng)
    src, dst, truth = correspondences(rng, 1000, outlier_ratio, pose)
    result = ransac(src, dst, INLIER_DISTANCE, seed=0)
    assert result.found
    assert_pose_close(result.transform, pose)
    assert result.scale == pytest.approx(1.0)
    np.testing.assert_array_equal(result.transform[3], [0.0, 0.0, 0.0, 1.0])
    # every true inlier is found; outliers that fall near their match by chance are few
    assert result.inliers[truth].all()
    assert result.num_inliers == result.inliers.sum() < truth.sum() * 1.1


def test_ransac_is_deterministic_given_the_seed(rng):
    pose = random_pose(rng)
    src, dst, _ = correspondences(rng, 1000, 0.8, pose)
    first, again = (ransac(src, dst, INLIER_DISTANCE, seed=7) for _ in range(2))
    np.testing.assert_array_equal(first.transform, again.transform)
    np.testing.assert_array_equal(first.inliers, again.inliers)
    assert first.iterations_run == again.iterations_run
    # another seed draws other hypotheses, but the refit on the same inliers lands on the pose
    assert_pose_close(ransac(src, dst, INLIER_DISTANCE, seed=8).transform, pose)


def test_ransac_stops_early_when_most_matches_are_inliers(rng):
    pose = random_pose(rng)
    src, dst, _ = correspondences(rng, 1000, 0.1, pose)
    easy = ransac(src, dst, INLIER_DISTANCE, seed=0, iterations=100_000)
    assert easy.iterations_run <= 64  # the first batch is enough
    assert_pose_close(easy.transform, pose)
    src, dst, _ = correspondences(rng, 1000, 0.9, pose)
    hard = ransac(src, dst, INLIER_DISTANCE, seed=0, iterations=100_000)
    # log(0.001) / log(1 - 0.1**3) is about 6,900 draws
    assert 3_000 < hard.iterations_run < 20_000


def test_ransac_respects_the_iteration_cap(rng):
    src, dst, _ = correspondences(rng, 500, 0.95, random_pose(rng))
    assert ransac(src, dst, INLIER_DISTANCE, seed=0, iterations=100, batch=32).iterations_run == 100


def test_ransac_estimates_a_similarity(rng):
    pose = random_pose(rng)
    src, dst, _ = correspondences(rng, 1000, 0.5, pose)
    dst = transform(src * 1.3, pose)
    dst[::2] = rng.uniform(dst.min(axis=0), dst.max(axis=0), size=(500, 3))
    result = ransac(src, dst, INLIER_DISTANCE, seed=0, estimate_scale=True)
    assert result.scale == pytest.approx(1.3, rel=1e-3)
    assert rotation_error_deg(result.rotation, pose[:3, :3]) < 1.0
    assert translation_error(result.translation, pose[:3, 3]) < 0.01
    rigid = ransac(src, dst, INLIER_DISTANCE, seed=0)
    assert rigid.num_inliers < result.num_inliers / 2


def test_ransac_refuses_too_few_correspondences():
    with pytest.raises(DegenerateInputError, match="at least 3 correspondences"):
        ransac(np.zeros((2, 3)), np.zeros((2, 3)), INLIER_DISTANCE, seed=0)
    with pytest.raises(InvalidInputError, match="one row per correspondence"):
        ransac(np.zeros((5, 3)), np.zeros((4, 3)), INLIER_DISTANCE, seed=0)
    with pytest.raises(InvalidInputError, match="inlier_distance"):
        ransac(np.ones((5, 3)), np.ones((5, 3)), 0.0, seed=0)


def test_ransac_finds_nothing_in_collinear_correspondences():
    line = np.linspace(0.0, 1.0, 50)[:, None] * np.array([1.0, 2.0, 3.0])
    result = ransac(line, line + 1.0, INLIER_DISTANCE, seed=0, iterations=2_000)
    assert not result.found and result.num_inliers == 0
    np.testing.assert_array_equal(result.transform, np.eye(4))


# --- the up prior ---------------------------------------------------------------------------


@pytest.fixture
def upright_and_tipped(rng) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Correspondences supporting two poses: 300 an upright one (model +Y to world +Z) and 400
    one tipped over by 90 degrees (+Y horizontal), plus 300 outliers. Without a prior the tipped
    pose wins on inlier count."""
    upright = make_pose(axis_angle(Z, 0.7) @ axis_angle(X, np.pi / 2), [1.0, 2.0, 0.45])
    tipped = make_pose(axis_angle(X, np.pi / 2) @ upright[:3, :3], [1.0, 2.0, 0.3])
    src = (rng.random((1000, 3)) - 0.5) * CHAIR_BOX
    dst = np.concatenate([transform(src[:300], upright), transform(src[300:700], tipped)])
    dst += rng.normal(scale=0.003, size=dst.shape)
    dst = np.concatenate([dst, rng.uniform(dst.min(axis=0), dst.max(axis=0), size=(300, 3))])
    return src, dst, upright, tipped


def tilt_deg(rotation: np.ndarray, up: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(rotation @ Y @ up, -1.0, 1.0))))


def test_up_prior_picks_the_upright_pose(upright_and_tipped):
    src, dst, upright, tipped = upright_and_tipped
    assert tilt_deg(tipped[:3, :3], Z) == pytest.approx(90.0)
    free = ransac(src, dst, INLIER_DISTANCE, seed=0)
    assert_pose_close(free.transform, tipped)
    prior = ransac(src, dst, INLIER_DISTANCE, seed=0, up=Z, up_tolerance_deg=20.0)
    assert tilt_deg(prior.rotation, Z) < 20.0
    assert_pose_close(prior.transform, upright)
    assert prior.inliers[:300].all() and prior.inliers[300:700].sum() < 20  # chance overlaps


def test_up_prior_filters_hypotheses(upright_and_tipped):
    src, dst, _, tipped = upright_and_tipped
    # an up that neither pose agrees with: only chance triplets of outliers survive
    down = ransac(src, dst, INLIER_DISTANCE, seed=0, up=-Z, up_tolerance_deg=20.0)
    assert down.num_inliers < 30
    assert not ransac(src, dst, INLIER_DISTANCE, seed=0, up=-Z, min_inliers=50).found
    # the up that the tipped pose implies selects it even with the upright inliers dropped
    sideways = tipped[:3, :3] @ Y
    kept = np.r_[300:1000]
    result = ransac(src[kept], dst[kept], INLIER_DISTANCE, seed=0, up=sideways)
    assert_pose_close(result.transform, tipped)
    with pytest.raises(InvalidInputError, match="non-zero"):
        ransac(src, dst, INLIER_DISTANCE, seed=0, up=np.zeros(3))


# --- against Open3D ---------------------------------------------------------------------------


def open3d_ransac(src: np.ndarray, dst: np.ndarray, distance: float, seed: int) -> np.ndarray:
    """What the FPFH baseline runs: source = model points, target = observed."""
    pairs = np.repeat(np.arange(len(src))[:, None], 2, axis=1)
    return open3d_recipe.open3d_ransac(point_cloud(src), point_cloud(dst), pairs, distance, seed)


def test_agrees_with_open3d(rng):
    pose = random_pose(rng)
    src, dst, _ = correspondences(rng, 1000, 0.8, pose)
    timings = {}
    for name, solve in [
        ("numpy", lambda seed: ransac(src, dst, INLIER_DISTANCE, seed=seed).transform),
        ("open3d", lambda seed: open3d_ransac(src, dst, INLIER_DISTANCE, seed)),
    ]:
        started = time.perf_counter()
        found = [solve(seed) for seed in range(3)]
        timings[name] = (time.perf_counter() - started) / 3
        for transform_ in found:
            # Open3D does not refit on all inliers at the end: a looser bound for both
            assert_pose_close(transform_, pose, deg=3.0, metres=0.02)
    print(
        f"\nRANSAC, 1000 matches, 80% outliers: numpy {timings['numpy'] * 1e3:.1f} ms, "
        f"Open3D {timings['open3d'] * 1e3:.1f} ms "
        f"(Open3D / numpy = {timings['open3d'] / timings['numpy']:.1f})"
    )


def test_one_point_matched_thrice_is_no_triangle(rng):
    """Most correspondences end on one observed point (a query point many model points
    matched): three of them fit a model shrunk onto it, scale 0, with all of them inliers."""
    pose = random_pose(rng)
    src = rng.uniform(-0.5, 0.5, size=(300, 3)) * CHAIR_BOX
    dst = transform(src, pose)
    dst[:200] = dst[0]
    # Every scale allowed: the triangle check alone must refuse the point.
    unbounded = (0.0, np.inf)
    result = ransac(src, dst, INLIER_DISTANCE, seed=0, estimate_scale=True, scale_range=unbounded)
    scale = np.cbrt(np.linalg.det(result.transform[:3, :3]))
    assert scale == pytest.approx(1.0, abs=1e-6)
    assert rotation_error_deg(result.transform[:3, :3] / scale, pose[:3, :3]) < 1e-4


@pytest.mark.parametrize("scale_range, found", [(SCALE_RANGE, False), ((0.5, 4.0), True)])
def test_a_scale_outside_the_range_is_not_an_answer(rng, scale_range, found):
    src = rng.uniform(-0.5, 0.5, size=(100, 3)) * CHAIR_BOX
    dst = 3.0 * src
    result = ransac(src, dst, INLIER_DISTANCE, seed=0, estimate_scale=True, scale_range=scale_range)
    assert result.found == found
    if found:
        np.testing.assert_allclose(result.transform[:3, :3], 3.0 * np.eye(3), atol=1e-9)
