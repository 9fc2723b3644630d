"""Sparse tensors and the coordinate manager behind them. A :class:`SparseTensor` is a feature
matrix (N, C) whose rows live on integer voxel coordinates (N, 4) = (batch, x, y, z) at a tensor
stride. The coordinates themselves are owned by a :class:`CoordinateManager` shared by every tensor
of one forward pass, which stores one coordinate set per stride and caches kernel maps, so each
map is built once per pass and reused by every layer (and by the transposed convolutions on the
way back up the U-Net).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from catalign.features.kernel_map import (
    KernelMap,
    build_kernel_map,
    check_unique,
    downsample_coords,
    kernel_offsets,
)


class CoordinateManager:
    """Coordinates per tensor stride plus a cache of kernel maps keyed by (strides, kernel size)."""

    def __init__(self) -> None:
        self._coords: dict[int, Tensor] = {}
        self._maps: dict[tuple[int, int, int], KernelMap] = {}

    def register(self, coords: Tensor, stride: int = 1, *, validate: bool = True) -> None:
        """Adopt ``coords`` as the coordinate set at ``stride`` (unique rows, multiples of it)."""
        if stride in self._coords:
            raise ValueError(f"coordinates at stride {stride} are already registered")
        if coords.ndim != 2 or coords.shape[1] != 4:
            raise ValueError(f"coordinates must have shape (N, 4), got {tuple(coords.shape)}")
        if coords.dtype not in (torch.int32, torch.int64):
            raise ValueError(f"coordinates must be int32 or int64, got {coords.dtype}")
        coords = coords.to(torch.int64).contiguous()
        if validate:
            check_unique(coords)
            if stride > 1 and bool((coords[:, 1:] % stride != 0).any()):
                raise ValueError(f"coordinates at stride {stride} must be multiples of it")
        self._coords[stride] = coords

    def strides(self) -> list[int]:
        return sorted(self._coords)

    def coords(self, stride: int) -> Tensor:
        try:
            return self._coords[stride]
        except KeyError:
            raise ValueError(f"no coordinates at tensor stride {stride}") from None

    def downsample(self, stride: int, factor: int) -> int:
        """Make sure the coarse set at ``stride * factor`` exists; return that stride."""
        out_stride = stride * factor
        if out_stride not in self._coords:
            coarse = downsample_coords(self.coords(stride), out_stride)
            self.register(coarse, out_stride, validate=False)
        return out_stride

    def kernel_map(self, in_stride: int, out_stride: int, kernel_size: int) -> KernelMap:
        """Map from the set at ``in_stride`` to the set at ``out_stride`` (cached).

        Equal strides give a submanifold map; a coarser output gives a strided map with offsets in
        units of the input stride; a finer output gives the transpose of the matching strided map,
        as MinkowskiEngine does for its (non-generative) transposed convolution.
        """
        key = (in_stride, out_stride, kernel_size)
        cached = self._maps.get(key)
        if cached is not None:
            return cached
        if in_stride > out_stride:
            kmap = self.kernel_map(out_stride, in_stride, kernel_size).transposed
        else:
            if out_stride % in_stride:
                raise ValueError(f"stride {out_stride} is not a multiple of {in_stride}")
            kmap = build_kernel_map(
                self.coords(in_stride),
                self.coords(out_stride),
                kernel_offsets(kernel_size, in_stride),
                submanifold=in_stride == out_stride,
                unit=in_stride,
            )
        self._maps[key] = kmap
        return kmap


class SparseTensor:
    """Features (N, C) on the coordinates a manager holds at ``stride``.

    Build one from coordinates with ``SparseTensor(features, coords)``; layers derive new tensors
    on the same manager with :meth:`with_features` or :meth:`on`.
    """

    __slots__ = ("features", "manager", "stride")

    def __init__(self, features: Tensor, coords: Tensor, stride: int = 1) -> None:
        manager = CoordinateManager()
        manager.register(coords.to(features.device), stride)
        self._init(features, manager, stride)

    def _init(self, features: Tensor, manager: CoordinateManager, stride: int) -> None:
        n = manager.coords(stride).shape[0]
        if features.ndim != 2 or features.shape[0] != n:
            raise ValueError(f"features must have shape ({n}, C), got {tuple(features.shape)}")
        self.features = features
        self.manager = manager
        self.stride = stride

    @classmethod
    def on(cls, features: Tensor, manager: CoordinateManager, stride: int) -> SparseTensor:
        """A tensor on coordinates the manager already holds."""
        out = cls.__new__(cls)
        out._init(features, manager, stride)
        return out

    @property
    def F(self) -> Tensor:  # MinkowskiEngine's name
        return self.features

    @property
    def C(self) -> Tensor:  # MinkowskiEngine's name
        return self.manager.coords(self.stride)

    @property
    def coords(self) -> Tensor:
        return self.manager.coords(self.stride)

    def __len__(self) -> int:
        return self.features.shape[0]

    def with_features(self, features: Tensor) -> SparseTensor:
        """Same coordinates, new features."""
        return SparseTensor.on(features, self.manager, self.stride)

    def same_sites(self, other: SparseTensor) -> bool:
        return self.manager is other.manager and self.stride == other.stride

    def __add__(self, other: SparseTensor) -> SparseTensor:
        if not self.same_sites(other):
            raise ValueError("can only add sparse tensors on the same coordinates")
        return self.with_features(self.features + other.features)

    def __repr__(self) -> str:
        n, c = self.features.shape
        return f"SparseTensor(n={n}, channels={c}, stride={self.stride})"


def batch_coords(coords_list: Sequence[Tensor]) -> Tensor:
    """Stack (M_i, 3) voxel coordinates into (sum M_i, 4) with the batch index first."""
    rows = [torch.cat([torch.full_like(c[:, :1], b), c], dim=1) for b, c in enumerate(coords_list)]
    return torch.cat(rows).to(torch.int64)


def sparse_collate(coords_list: Sequence[Tensor], features_list: Sequence[Tensor]) -> SparseTensor:
    """One batched sparse tensor from per-cloud (M_i, 3) coordinates and (M_i, C) features."""
    return SparseTensor(torch.cat(list(features_list)), batch_coords(coords_list))
