from __future__ import annotations

import numpy as np
import pytest

from catalign.geometry.ncc import NCCFrame, to_ncc


@pytest.fixture
def points(rng) -> np.ndarray:
    return rng.normal(size=(500, 3)) * [0.3, 0.8, 0.2] + [5.0, -2.0, 1.0]


def test_round_trip(points):
    frame = NCCFrame.fit(points)
    np.testing.assert_allclose(frame.from_ncc(frame.to_ncc(points)), points, atol=1e-12)
    np.testing.assert_allclose(frame.to_ncc(frame.from_ncc(points)), points, atol=1e-12)


def test_ncc_has_unit_diagonal_and_centred_bbox(points):
    ncc = to_ncc(points)
    lo, hi = ncc.min(axis=0), ncc.max(axis=0)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-12)
    # aspect ratios are kept (a similarity, not a per-axis stretch)
    extents = np.ptp(points, axis=0)
    np.testing.assert_allclose(np.ptp(ncc, axis=0), extents / np.linalg.norm(extents))


def test_fit_on_a_known_box():
    corners = np.array([[0.0, 0.0, 0.0], [2.0, 3.0, 6.0], [1.0, 1.0, 1.0]])
    frame = NCCFrame.fit(corners)
    np.testing.assert_allclose(frame.centre, [1.0, 1.5, 3.0])
    assert frame.scale == pytest.approx(7.0)


def test_matrix_agrees_with_to_ncc(points):
    frame = NCCFrame.fit(points)
    matrix = frame.matrix()
    homogeneous = np.c_[points, np.ones(len(points))] @ matrix.T
    np.testing.assert_allclose(homogeneous[:, :3], frame.to_ncc(points), atol=1e-12)
    np.testing.assert_allclose(homogeneous[:, 3], 1.0)
    np.testing.assert_array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0])


def test_scale_invariance(points):
    np.testing.assert_allclose(to_ncc(points * 3.0 + 1.0), to_ncc(points), atol=1e-12)


@pytest.mark.parametrize("points", [np.ones((10, 3)), np.zeros((1, 3))])
def test_coincident_points_raise(points):
    with pytest.raises(ValueError, match="coincide"):
        NCCFrame.fit(points)
