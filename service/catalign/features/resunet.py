"""FCGF's fully convolutional feature extractor (ResUNetBN2C and narrower variants) on the
pure-PyTorch sparse convolution in :mod:`catalign.features.sparse`, plus the inference helpers
that turn a raw point cloud into per-voxel unit-norm descriptors. The stage structure follows
Choy et al.'s ``ResUNet2``: four encoder stages (stride 1, 2, 4, 8), each a convolution, batch
norm and residual block; three transposed-convolution decoder stages with skip concatenations;
a 1x1 fusion, a 1x1 output layer and L2 normalisation. Configuration is plain JSON-able data so
checkpoints hold weights and a dict, never pickled objects.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from catalign.errors import ConfigError, InvalidInputError
from catalign.features.kernel_map import coordinate_keys
from catalign.features.sparse import (
    SparseBatchNorm,
    SparseConv3d,
    SparseConvTranspose3d,
    SparseTensor,
    sparse_cat,
    sparse_relu,
)
from catalign.features.sparse_tensor import batch_coords


class UnknownModelError(ConfigError, ValueError):
    """``build_model`` got a name it does not know."""


class InvalidPointsError(InvalidInputError, ValueError):
    """Points that cannot be voxelised: wrong shape, non-finite, empty, or a bad voxel size."""


class BasicBlock(nn.Module):
    """Residual block: conv3-BN-ReLU-conv3-BN, plus the input, then ReLU (FCGF's BasicBlockBN)."""

    def __init__(self, channels: int, bn_momentum: float) -> None:
        super().__init__()
        self.conv1 = SparseConv3d(channels, channels, kernel_size=3)
        self.norm1 = SparseBatchNorm(channels, momentum=bn_momentum)
        self.conv2 = SparseConv3d(channels, channels, kernel_size=3)
        self.norm2 = SparseBatchNorm(channels, momentum=bn_momentum)

    def forward(self, x: SparseTensor) -> SparseTensor:
        out = sparse_relu(self.norm1(self.conv1(x)))
        out = self.norm2(self.conv2(out))
        return sparse_relu(out + x)


class _Stage(nn.Module):
    """Convolution (strided or transposed), batch norm and a residual block."""

    def __init__(self, conv: nn.Module, channels: int, bn_momentum: float) -> None:
        super().__init__()
        self.conv = conv
        self.norm = SparseBatchNorm(channels, momentum=bn_momentum)
        self.block = BasicBlock(channels, bn_momentum)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return self.block(self.norm(self.conv(x)))


class ResUNet2(nn.Module):
    """FCGF ResUNet2 family; subclasses only change the channel lists.

    ``CHANNELS[i]`` is the encoder width at stride 2**(i-1); ``TR_CHANNELS[i]`` the decoder width
    there (index 0 unused, as in FCGF).
    """

    CHANNELS: ClassVar[tuple[int, ...]] = (0, 32, 64, 128, 256)
    TR_CHANNELS: ClassVar[tuple[int, ...]] = (0, 32, 64, 64, 128)

    def __init__(
        self,
        in_channels: int = 1,
        out_channels: int = 32,
        conv1_kernel_size: int = 5,
        bn_momentum: float = 0.05,
        normalize_feature: bool = True,
    ) -> None:
        super().__init__()
        self._config = {
            "name": type(self).__name__,
            "in_channels": int(in_channels),
            "out_channels": int(out_channels),
            "conv1_kernel_size": int(conv1_kernel_size),
            "bn_momentum": float(bn_momentum),
            "normalize_feature": bool(normalize_feature),
        }
        ch, tr, m = self.CHANNELS, self.TR_CHANNELS, bn_momentum

        def down(c_in: int, c_out: int) -> _Stage:
            return _Stage(SparseConv3d(c_in, c_out, kernel_size=3, stride=2), c_out, m)

        def up(c_in: int, c_out: int) -> _Stage:
            return _Stage(SparseConvTranspose3d(c_in, c_out, kernel_size=3, stride=2), c_out, m)

        conv1 = SparseConv3d(in_channels, ch[1], kernel_size=conv1_kernel_size)
        self.enc1 = _Stage(conv1, ch[1], m)
        self.enc2 = down(ch[1], ch[2])
        self.enc3 = down(ch[2], ch[3])
        self.enc4 = down(ch[3], ch[4])
        self.dec4 = up(ch[4], tr[4])
        self.dec3 = up(ch[3] + tr[4], tr[3])
        self.dec2 = up(ch[2] + tr[3], tr[2])
        self.fuse = SparseConv3d(ch[1] + tr[2], tr[1], kernel_size=1)
        self.final = SparseConv3d(tr[1], out_channels, kernel_size=1, bias=True)
        self.normalize_feature = normalize_feature

    @property
    def config(self) -> dict[str, Any]:
        """JSON-serialisable settings; ``build_model(**model.config)`` rebuilds the model."""
        return dict(self._config)

    def forward(self, x: SparseTensor) -> SparseTensor:
        # Every stage ends in its block's ReLU, so FCGF's extra MEF.relu calls are identities.
        out_s1 = self.enc1(x)
        out_s2 = self.enc2(out_s1)
        out_s4 = self.enc3(out_s2)
        out_s8 = self.enc4(out_s4)

        up_s4 = self.dec4(out_s8)
        up_s2 = self.dec3(sparse_cat(up_s4, out_s4))
        up_s1 = self.dec2(sparse_cat(up_s2, out_s2))

        out = sparse_relu(self.fuse(sparse_cat(up_s1, out_s1)))
        out = self.final(out)
        if not self.normalize_feature:
            return out
        return out.with_features(nn.functional.normalize(out.features, p=2.0, dim=1))


class ResUNetBN2C(ResUNet2):
    """The FCGF model used for 3DMatch/KITTI descriptors (about 8.8 M parameters)."""

    CHANNELS = (0, 32, 64, 128, 256)
    TR_CHANNELS = (0, 64, 64, 64, 128)


class ResUNetSmall(ResUNet2):
    """BN2C at half width: a quarter of the multiply-adds, for CPU-bound inference."""

    CHANNELS = (0, 16, 32, 64, 128)
    TR_CHANNELS = (0, 32, 32, 32, 64)


MODELS: dict[str, type[ResUNet2]] = {cls.__name__: cls for cls in (ResUNetBN2C, ResUNetSmall)}


def build_model(name: str, **kwargs: Any) -> ResUNet2:
    """Instantiate a registered model by class name; ``build_model(**model.config)`` round-trips."""
    try:
        cls = MODELS[name]
    except KeyError:
        raise UnknownModelError(
            f"unknown feature model {name!r}; known: {', '.join(sorted(MODELS))}"
        ) from None
    return cls(**kwargs)


class Voxelization(NamedTuple):
    """``coords`` (M, 3) int64 voxel indices, sorted; ``point_index`` (M,) the first point in each
    voxel; ``inverse`` (N,) the voxel of every point."""

    coords: Tensor
    point_index: Tensor
    inverse: Tensor


def _as_points(points: np.ndarray | Tensor) -> Tensor:
    pts = torch.as_tensor(np.asarray(points) if not isinstance(points, Tensor) else points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidPointsError(f"points must have shape (N, 3), got {tuple(pts.shape)}")
    if pts.shape[0] == 0:
        raise InvalidPointsError("points are empty")
    if not pts.is_floating_point():
        pts = pts.to(torch.float64)
    if not bool(torch.isfinite(pts).all()):
        raise InvalidPointsError("points contain NaN or infinite values")
    return pts


def _voxelize(pts: Tensor, voxel_size: float) -> Voxelization:
    if not voxel_size > 0:
        raise InvalidPointsError(f"voxel_size must be positive, got {voxel_size}")
    grid = torch.floor(pts.to(torch.float64) / voxel_size).to(torch.int64)
    keyed = torch.cat([torch.zeros_like(grid[:, :1]), grid], dim=1)
    _, inverse = torch.unique(coordinate_keys(keyed), return_inverse=True)
    n_vox = int(inverse.max()) + 1
    rows = torch.arange(grid.shape[0], device=grid.device)
    first = torch.full((n_vox,), grid.shape[0], dtype=torch.int64, device=grid.device)
    first.scatter_reduce_(0, inverse, rows, reduce="amin")
    return Voxelization(grid[first], first, inverse)


def voxelize(points: np.ndarray | Tensor, voxel_size: float) -> Voxelization:
    """Quantise to ``floor(points / voxel_size)`` and keep one voxel per occupied cell."""
    return _voxelize(_as_points(points), voxel_size)


def extract_features(
    model: ResUNet2, points: np.ndarray | Tensor, voxel_size: float
) -> tuple[Tensor, Tensor]:
    """Per-voxel descriptors of one cloud: (voxel centroids (M, 3) float32, features (M, C)).

    Runs in eval and inference mode (restoring the model's mode after); returns CPU float32
    tensors. The centroid is the mean of the points in the voxel, which keeps keypoints on the
    surface.
    """
    return extract_features_batch(model, [points], voxel_size)[0]


def extract_features_batch(
    model: ResUNet2, clouds: Sequence[np.ndarray | Tensor], voxel_size: float
) -> list[tuple[Tensor, Tensor]]:
    """:func:`extract_features` of several clouds in one forward pass.

    Batch norm runs on its stored statistics in eval mode and convolutions never cross the
    batch index, so each cloud gets the features it would alone; one pass saves the per-layer
    overhead that dominates small clouds (a query described at 8 headings).
    """
    coords, centroids = [], []
    for points in clouds:
        pts = _as_points(points).to(torch.float64)
        vox = _voxelize(pts, voxel_size)
        n_vox = vox.coords.shape[0]
        sums = torch.zeros(n_vox, 3, dtype=torch.float64).index_add_(0, vox.inverse, pts)
        counts = torch.bincount(vox.inverse, minlength=n_vox).to(torch.float64)
        centroids.append((sums / counts[:, None]).to(torch.float32))
        coords.append(vox.coords)

    param = next(model.parameters())
    batched = batch_coords(coords)
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            ones = torch.ones(len(batched), model.config["in_channels"], dtype=param.dtype)
            out = model(SparseTensor(ones.to(param.device), batched.to(param.device)))
            features = out.features.to("cpu", torch.float32)
    finally:
        model.train(was_training)  # a validation call inside a training loop must not flip modes
    parts = features.split([len(c) for c in coords])
    return list(zip(centroids, parts, strict=True))
