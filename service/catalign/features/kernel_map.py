"""Kernel maps for sparse convolution: which input voxel feeds which output voxel through which
kernel offset. Coordinates are (batch, x, y, z) integer rows in MinkowskiEngine's convention
(in units of the finest voxel, so a tensor at stride ``s`` holds multiples of ``s``). Maps are
found by packing coordinates into int64 keys that are linear in x, y, z, and looking every
(output + offset) key up among the input keys: by sorting them once and ``torch.searchsorted``
(any coordinate range), or, when the keys span a compact box as for one object, through a dense
key-indexed array. The result is a flat list of (input, output) row pairs grouped by offset,
which is what the gather-matmul-scatter convolution consumes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

_KEY_LIMIT = 2**62
_GRID_LIMIT = 2**24  # dense lookup arrays up to 128 MiB of int64


def kernel_offsets(kernel_size: int, tensor_stride: int = 1) -> Tensor:
    """(K, 3) int64 offsets, ordered like ``conv3d`` weights ``w[:, :, a, b, c]`` (c fastest).

    Odd kernels are centred (-r..r); even kernels start at 0 (0..k-1), as in MinkowskiEngine, so a
    kernel-2 stride-2 convolution covers exactly the fine voxels of each coarse voxel.
    """
    if kernel_size < 1:
        raise ValueError(f"kernel_size must be >= 1, got {kernel_size}")
    start = -((kernel_size - 1) // 2) if kernel_size % 2 else 0
    r = torch.arange(start, start + kernel_size, dtype=torch.int64)
    grid = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), dim=-1).reshape(-1, 3)
    return grid * tensor_stride


class _HashSpace:
    """A packing of (batch, x, y, z) into one int64 that is linear in x, y, z.

    Linearity lets ``key(c + d) == key(c) + key_delta(d)``, so the queries for all offsets are one
    broadcast add; the box is padded by ``reach`` so shifted queries never wrap.
    """

    def __init__(self, coord_sets: list[Tensor], reach: int) -> None:
        lo = torch.stack([c[:, 1:].amin(0) for c in coord_sets]).amin(0) - reach
        hi = torch.stack([c[:, 1:].amax(0) for c in coord_sets]).amax(0) + reach
        if min(int(c[:, 0].amin()) for c in coord_sets) < 0:
            raise ValueError("batch indices must be >= 0")
        n_batch = max(int(c[:, 0].amax()) for c in coord_sets) + 1
        self.lo = lo
        self.s0, self.s1, self.s2 = (int(s) for s in (hi - lo + 1).tolist())
        self.volume = n_batch * self.s0 * self.s1 * self.s2
        if self.volume >= _KEY_LIMIT:
            raise ValueError("coordinate range too large to hash into int64 keys")

    def keys(self, coords: Tensor) -> Tensor:
        c = coords[:, 1:] - self.lo
        return ((coords[:, 0] * self.s0 + c[:, 0]) * self.s1 + c[:, 1]) * self.s2 + c[:, 2]

    def deltas(self, offsets: Tensor) -> Tensor:
        return (offsets[:, 0] * self.s1 + offsets[:, 1]) * self.s2 + offsets[:, 2]


def coordinate_keys(coords: Tensor) -> Tensor:
    """Collision-free int64 keys of (N, 4) coordinates, ordered batch-major then x, y, z."""
    return _HashSpace([coords], 0).keys(coords)


def check_unique(coords: Tensor) -> None:
    """Raise ValueError when two rows are equal: duplicate sites break the hash lookups."""
    if coords.shape[0] < 2:
        return
    keys, _ = torch.sort(coordinate_keys(coords))
    if bool((keys[1:] == keys[:-1]).any()):
        raise ValueError("sparse tensor coordinates must be unique (voxelise first)")


def downsample_coords(coords: Tensor, out_stride: int) -> Tensor:
    """Unique ``floor(c / out_stride) * out_stride`` rows, sorted (ME's strided sites)."""
    if coords.shape[0] == 0:
        return coords.clone()
    coarse = coords.clone()
    coarse[:, 1:] = torch.div(coarse[:, 1:], out_stride, rounding_mode="floor") * out_stride
    _, inverse = torch.unique(coordinate_keys(coarse), return_inverse=True)
    n_out = int(inverse.max()) + 1
    rows = torch.arange(coarse.shape[0], device=coords.device)
    first = torch.full((n_out,), coarse.shape[0], dtype=torch.int64, device=coords.device)
    first.scatter_reduce_(0, inverse, rows, reduce="amin")
    return coarse[first]


@dataclass(frozen=True, eq=False)
class KernelMap:
    """Pairs (in_idx[p], out_idx[p]) contributing through offset k, grouped by k.

    ``segments`` lists (k, start, end) over the pair arrays for non-empty offsets only, so the
    convolution never loops over empty offsets. ``identity_offset`` marks a submanifold centre
    offset whose pairs are all (i, i); it is kept out of the pair arrays and done as one matmul.
    """

    in_idx: Tensor
    out_idx: Tensor
    segments: tuple[tuple[int, int, int], ...]
    n_in: int
    n_out: int
    kernel_volume: int
    identity_offset: int | None = None

    @property
    def n_pairs(self) -> int:
        extra = self.n_out if self.identity_offset is not None else 0
        return int(self.in_idx.numel()) + extra

    @cached_property
    def segment_sizes(self) -> list[int]:
        return [end - start for _, start, end in self.segments]

    @cached_property
    def segment_offsets(self) -> list[int]:
        return [k for k, _, _ in self.segments]

    @cached_property
    def transposed(self) -> KernelMap:
        """The same pairs read backwards: the map of the transposed convolution."""
        return KernelMap(
            in_idx=self.out_idx,
            out_idx=self.in_idx,
            segments=self.segments,
            n_in=self.n_out,
            n_out=self.n_in,
            kernel_volume=self.kernel_volume,
            identity_offset=self.identity_offset,
        )

    @cached_property
    def gather_table(self) -> Tensor:
        """(n_out, K) input row per output and offset, ``n_in`` (a zero pad row) where none."""
        table = torch.full(
            (self.n_out, self.kernel_volume),
            self.n_in,
            dtype=torch.int64,
            device=self.in_idx.device,
        )
        if self.identity_offset is not None:
            table[:, self.identity_offset] = torch.arange(self.n_out, device=table.device)
        if self.segments:
            ks = torch.tensor([k for k, _, _ in self.segments], device=table.device)
            lengths = torch.tensor([e - b for _, b, e in self.segments], device=table.device)
            table[self.out_idx, ks.repeat_interleave(lengths)] = self.in_idx
        return table


def _scaled(coords: Tensor, unit: int) -> Tensor:
    if unit == 1:
        return coords
    out = coords.clone()
    out[:, 1:] = torch.div(out[:, 1:], unit, rounding_mode="floor")
    return out


def build_kernel_map(
    in_coords: Tensor,
    out_coords: Tensor,
    offsets: Tensor,
    *,
    submanifold: bool = False,
    unit: int = 1,
    lookup: str = "auto",
) -> KernelMap:
    """All pairs with ``in_coords[i] == out_coords[j] + offsets[k]`` in the same batch.

    ``submanifold=True`` asserts ``in_coords is out_coords``; the zero offset is then the identity.
    ``unit`` divides every coordinate and offset first (all are multiples of the finer tensor
    stride), which keeps the key space small. ``lookup`` is "sorted" (sort + searchsorted, any
    range), "grid" (a dense key-indexed array, for compact boxes) or "auto".
    """
    n_in, n_out, n_k = in_coords.shape[0], out_coords.shape[0], offsets.shape[0]
    device = in_coords.device
    offsets = offsets.to(device)
    identity = None
    if submanifold:
        zero = (offsets == 0).all(1).nonzero()
        identity = int(zero[0, 0]) if zero.numel() else None
    empty = torch.zeros(0, dtype=torch.int64, device=device)
    if n_in == 0 or n_out == 0:
        return KernelMap(empty, empty, (), n_in, n_out, n_k, identity if n_in else None)

    in_c, out_c = _scaled(in_coords, unit), _scaled(out_coords, unit)
    offsets = torch.div(offsets, unit, rounding_mode="floor")
    # A submanifold map is symmetric: offset -d holds the swapped pairs of +d, and with the
    # conv3d ordering -d is offset K-1-k. Look up only the offsets before the centre.
    mirror = identity is not None and identity == n_k // 2 and n_k % 2 == 1
    columns = list(range(n_k // 2)) if mirror else [k for k in range(n_k) if k != identity]
    if not columns:
        return KernelMap(empty, empty, (), n_in, n_out, n_k, identity)
    space = _HashSpace([in_c, out_c], int(offsets.abs().max()))
    deltas = space.deltas(offsets[columns])
    query = (space.keys(out_c)[None, :] + deltas[:, None]).view(-1)  # offset-major
    if lookup == "auto":
        lookup = "grid" if space.volume <= min(4 * query.numel() + 4096, _GRID_LIMIT) else "sorted"
    if lookup == "grid":
        grid = torch.full((space.volume,), -1, dtype=torch.int64, device=device)
        grid[space.keys(in_c)] = torch.arange(n_in, device=device)
        found = grid.index_select(0, query)
    elif lookup == "sorted":
        sorted_keys, order = torch.sort(space.keys(in_c))
        pos = torch.searchsorted(sorted_keys, query).clamp_(max=n_in - 1)
        found = torch.where(
            sorted_keys.index_select(0, pos) == query, order.index_select(0, pos), -1
        )
    else:
        raise ValueError(f"unknown lookup {lookup!r}")
    hits = (found >= 0).nonzero().squeeze(1)  # ascending: grouped by offset, then output row
    in_idx = found.index_select(0, hits)
    col = torch.div(hits, n_out, rounding_mode="floor")
    out_idx = hits - col * n_out
    bounds = torch.arange(len(columns) + 1, device=device) * n_out
    ends = torch.searchsorted(hits, bounds).tolist()
    segments = [(k, ends[c], ends[c + 1]) for c, k in enumerate(columns) if ends[c + 1] > ends[c]]
    if mirror:
        n = int(hits.numel())
        segments += [(n_k - 1 - k, n + b, n + e) for k, b, e in segments]
        in_idx, out_idx = torch.cat([in_idx, out_idx]), torch.cat([out_idx, in_idx])
    return KernelMap(in_idx, out_idx, tuple(segments), n_in, n_out, n_k, identity)
