"""ResUNet feature extractor: shapes, unit norm, determinism, gradient flow, invariance to
translations by whole coarse voxels, batch independence, config round trip and the voxelisation
and extraction helpers. Uses small clouds (a few hundred voxels) so the file runs in seconds.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from catalign.errors import ConfigError, InvalidInputError
from catalign.features.resunet import (
    ResUNetBN2C,
    ResUNetSmall,
    build_model,
    extract_features,
    extract_features_batch,
    voxelize,
)
from catalign.features.sparse import SparseTensor
from catalign.features.sparse_tensor import batch_coords, sparse_collate

VOXEL = 0.05


def _cloud(seed: int, n: int = 3000) -> np.ndarray:
    """A sphere shell over a floor patch: a surface with some structure, ~0.8 m across."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n // 2, 3))
    sphere = 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True) + [0.0, 0.0, 0.4]
    floor = np.c_[rng.uniform(-0.4, 0.4, (n - n // 2, 2)), np.zeros(n - n // 2)]
    return np.concatenate([sphere, floor]).astype(np.float32)


def _voxels(seed: int) -> torch.Tensor:
    return voxelize(_cloud(seed), VOXEL).coords


def _ones(coords: torch.Tensor) -> SparseTensor:
    return SparseTensor(torch.ones(coords.shape[0], 1), batch_coords([coords]))


@pytest.fixture(scope="module")
def small_model() -> ResUNetSmall:
    torch.manual_seed(0)
    model = ResUNetSmall(conv1_kernel_size=3)
    # Non-trivial running statistics, so eval mode is not a plain identity normalisation.
    model.train()
    with torch.no_grad():
        for seed in range(3):
            model(_ones(_voxels(seed)))
    return model.eval()


def test_extract_features_shape_and_unit_norm() -> None:
    torch.manual_seed(0)
    model = ResUNetBN2C()
    points = _cloud(1)
    centroids, feats = extract_features(model, points, VOXEL)
    n_vox = voxelize(points, VOXEL).coords.shape[0]
    assert centroids.shape == (n_vox, 3) and centroids.dtype == torch.float32
    assert feats.shape == (n_vox, 32) and feats.dtype == torch.float32
    torch.testing.assert_close(feats.norm(dim=1), torch.ones(n_vox), atol=1e-5, rtol=0)
    assert model.training  # the caller's mode is restored


def test_centroids_lie_in_their_voxels() -> None:
    points = _cloud(2)
    vox = voxelize(points, VOXEL)
    centroids, _ = extract_features(ResUNetSmall(), points, VOXEL)
    cells = torch.floor(centroids.double() / VOXEL).long()
    assert torch.equal(cells, vox.coords)


def test_eval_is_deterministic(small_model: ResUNetSmall) -> None:
    points = _cloud(3)
    _, a = extract_features(small_model, points, VOXEL)
    _, b = extract_features(small_model, points, VOXEL)
    assert torch.equal(a, b)


def test_a_batch_of_clouds_gets_the_features_each_would_get_alone(
    small_model: ResUNetSmall,
) -> None:
    clouds = [_cloud(6), _cloud(7, n=1500) + 0.3, _cloud(8)]
    batched = extract_features_batch(small_model, clouds, VOXEL)
    assert len(batched) == len(clouds)
    for cloud, (centroids, features) in zip(clouds, batched, strict=True):
        alone_centroids, alone_features = extract_features(small_model, cloud, VOXEL)
        assert torch.equal(centroids, alone_centroids)
        torch.testing.assert_close(features, alone_features, atol=1e-5, rtol=0)


def test_gradients_reach_every_parameter() -> None:
    torch.manual_seed(0)
    model = ResUNetSmall().train()
    a, b = _voxels(4), _voxels(5)
    x = sparse_collate([a, b], [torch.ones(a.shape[0], 1), torch.ones(b.shape[0], 1)])
    loss = (model(x).features * torch.randn(len(x), 32)).sum()
    loss.backward()
    for name, param in model.named_parameters():
        assert param.grad is not None, name
        assert torch.isfinite(param.grad).all(), name
        assert param.grad.abs().sum() > 0, name


def test_translation_by_whole_coarse_voxels_keeps_features(small_model: ResUNetSmall) -> None:
    """Shifts by multiples of the coarsest stride (8 voxels) keep every pooling cell intact."""
    coords = _voxels(6)
    with torch.inference_mode():
        base = small_model(_ones(coords)).features
        shifted = small_model(_ones(coords + torch.tensor([8, -16, 24]))).features
    torch.testing.assert_close(shifted, base, atol=1e-5, rtol=1e-5)


def test_batch_of_two_equals_each_alone(small_model: ResUNetSmall) -> None:
    a, b = _voxels(7), _voxels(8)
    with torch.inference_mode():
        both = small_model(
            sparse_collate([a, b], [torch.ones(a.shape[0], 1), torch.ones(b.shape[0], 1)])
        ).features
        alone_a = small_model(_ones(a)).features
        alone_b = small_model(_ones(b)).features
    torch.testing.assert_close(both[: a.shape[0]], alone_a, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(both[a.shape[0] :], alone_b, atol=1e-5, rtol=1e-5)


def test_config_round_trip_is_plain_data(small_model: ResUNetSmall) -> None:
    config = json.loads(json.dumps(small_model.config))
    rebuilt = build_model(**config)
    assert type(rebuilt) is ResUNetSmall and rebuilt.config == small_model.config
    rebuilt.load_state_dict(small_model.state_dict())
    points = _cloud(9)
    _, a = extract_features(small_model, points, VOXEL)
    _, b = extract_features(rebuilt, points, VOXEL)
    assert torch.equal(a, b)


def test_channel_lists_define_the_variants() -> None:
    big, small = ResUNetBN2C(), ResUNetSmall()
    assert big.enc4.conv.out_channels == 256 and small.enc4.conv.out_channels == 128
    assert big.final.out_channels == small.final.out_channels == 32
    assert sum(p.numel() for p in big.parameters()) == 8_753_408  # FCGF's ResUNetBN2C
    assert build_model("ResUNetBN2C", out_channels=16).final.out_channels == 16


def test_unknown_model_name() -> None:
    with pytest.raises(ValueError, match="unknown feature model"):
        build_model("PointNet")
    with pytest.raises(ConfigError):
        build_model("PointNet")


def test_voxelize_maps_points_to_cells() -> None:
    points = _cloud(10)
    vox = voxelize(points, VOXEL)
    expected = torch.floor(torch.from_numpy(points).double() / VOXEL).long()
    assert torch.equal(vox.coords[vox.inverse], expected)
    assert torch.equal(expected[vox.point_index], vox.coords)
    assert vox.coords.unique(dim=0).shape[0] == vox.coords.shape[0]
    same = voxelize(torch.from_numpy(points), VOXEL)
    assert torch.equal(same.coords, vox.coords)


@pytest.mark.parametrize(
    "points",
    [np.zeros((0, 3)), np.zeros((5, 2)), np.array([[0.0, np.nan, 1.0]])],
    ids=["empty", "2d", "nan"],
)
def test_voxelize_rejects_bad_points(points: np.ndarray) -> None:
    with pytest.raises(InvalidInputError):
        voxelize(points, VOXEL)
    with pytest.raises(ValueError):
        voxelize(points, VOXEL)


def test_voxelize_rejects_bad_voxel_size() -> None:
    with pytest.raises(ValueError, match="voxel_size"):
        voxelize(_cloud(0), 0.0)
