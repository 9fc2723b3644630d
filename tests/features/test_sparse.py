"""Sparse convolution against dense references: ``conv3d`` / ``conv_transpose3d`` on small grids
with inactive sites zeroed and outputs read at the active sites (which is exactly what a
submanifold / MinkowskiEngine strided / transposed convolution computes), forward and backward,
in float64, for every kernel size, both compute kernels and both kernel-map lookups.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from catalign.features.kernel_map import build_kernel_map, downsample_coords, kernel_offsets
from catalign.features.sparse import (
    SparseBatchNorm,
    SparseConv3d,
    SparseConvTranspose3d,
    SparseTensor,
    sparse_cat,
    sparse_conv,
)
from catalign.features.sparse_tensor import CoordinateManager, sparse_collate

DT = torch.float64
TOL = {"atol": 1e-10, "rtol": 1e-9}


def _active_grid(n: int, density: float, seed: int) -> torch.Tensor:
    """(M, 3) int64 indices of active cells of an n^3 grid (at least a few)."""
    gen = torch.Generator().manual_seed(seed)
    mask = torch.rand(n, n, n, generator=gen) < density
    mask[0, 0, 0] = mask[n - 1, n - 1, n - 1] = True
    return mask.nonzero()


def _with_batch(idx: torch.Tensor, origin: int = 0, batch: int = 0) -> torch.Tensor:
    return torch.cat([torch.full_like(idx[:, :1], batch), idx + origin], dim=1)


def _dense(idx: torch.Tensor, feats: torch.Tensor, n: int) -> torch.Tensor:
    """(1, C, n, n, n) grid with ``feats`` at ``idx`` and zeros elsewhere (differentiable)."""
    grid = feats.new_zeros(n, n, n, feats.shape[1])
    grid = grid.index_put((idx[:, 0], idx[:, 1], idx[:, 2]), feats)
    return grid.permute(3, 0, 1, 2).unsqueeze(0)


def _read(dense: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    return dense[0][:, idx[:, 0], idx[:, 1], idx[:, 2]].t()


def _conv_weight(w: torch.Tensor, k: int) -> torch.Tensor:
    """(K, Cin, Cout) -> conv3d layout (Cout, Cin, k, k, k)."""
    return w.permute(2, 1, 0).reshape(w.shape[2], w.shape[1], k, k, k)


def _tr_weight(w: torch.Tensor, k: int) -> torch.Tensor:
    """(K, Cin, Cout) -> conv_transpose3d layout (Cin, Cout, k, k, k)."""
    return w.permute(1, 2, 0).reshape(w.shape[1], w.shape[2], k, k, k)


def _leaves(*shapes: tuple[int, ...], seed: int) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return [torch.randn(*s, generator=gen, dtype=DT).requires_grad_() for s in shapes]


def _grads(out: torch.Tensor, probe: torch.Tensor, *leaves: torch.Tensor) -> list[torch.Tensor]:
    return list(torch.autograd.grad((out * probe).sum(), leaves))


METHODS = ["pairs", "dense"]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    ("kernel", "n", "density"), [(1, 5, 0.5), (3, 6, 0.4), (5, 6, 0.3), (7, 7, 0.25)]
)
def test_submanifold_matches_masked_conv3d(
    kernel: int, n: int, density: float, method: str
) -> None:
    idx = _active_grid(n, density, seed=kernel)
    coords = _with_batch(idx, origin=-3)  # negative coordinates on purpose
    x, w = _leaves((idx.shape[0], 3), (kernel**3, 3, 4), seed=1)
    kmap = build_kernel_map(coords, coords, kernel_offsets(kernel), submanifold=True)
    out = sparse_conv(x, w, kmap, method=method)
    dense = F.conv3d(_dense(idx, x, n), _conv_weight(w, kernel), padding=kernel // 2)
    ref = _read(dense, idx)
    torch.testing.assert_close(out, ref, **TOL)

    probe = torch.randn_like(out)
    for got, want in zip(_grads(out, probe, x, w), _grads(ref, probe, x, w), strict=True):
        torch.testing.assert_close(got, want, **TOL)


def test_fully_occupied_grid_equals_conv3d_everywhere() -> None:
    n, k = 4, 3
    idx = torch.cartesian_prod(torch.arange(n), torch.arange(n), torch.arange(n))
    x, w = _leaves((idx.shape[0], 2), (k**3, 2, 3), seed=2)
    conv = SparseConv3d(2, 3, kernel_size=k).double()
    with torch.no_grad():
        conv.weight.copy_(w)
    out = conv(SparseTensor(x, _with_batch(idx))).features
    ref = _read(F.conv3d(_dense(idx, x, n), _conv_weight(w, k), padding=1), idx)
    torch.testing.assert_close(out, ref, **TOL)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("kernel", [2, 3])
def test_strided_matches_conv3d_stride2(kernel: int, method: str) -> None:
    n = 6
    idx = _active_grid(n, 0.3, seed=10 + kernel)
    coords = _with_batch(idx, origin=-4)  # even origin keeps the coarse grid aligned with conv3d
    x, w = _leaves((idx.shape[0], 3), (kernel**3, 3, 5), seed=3)
    coarse = downsample_coords(coords, 2)
    kmap = build_kernel_map(coords, coarse, kernel_offsets(kernel))
    out = sparse_conv(x, w, kmap, method=method)
    pad = 1 if kernel == 3 else 0
    dense = F.conv3d(_dense(idx, x, n), _conv_weight(w, kernel), stride=2, padding=pad)
    ref = _read(dense, torch.div(coarse[:, 1:] + 4, 2, rounding_mode="floor"))
    torch.testing.assert_close(out, ref, **TOL)

    probe = torch.randn_like(out)
    for got, want in zip(_grads(out, probe, x, w), _grads(ref, probe, x, w), strict=True):
        torch.testing.assert_close(got, want, **TOL)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("kernel", [2, 3])
def test_transposed_matches_conv_transpose3d(kernel: int, method: str) -> None:
    n = 6
    idx = _active_grid(n, 0.3, seed=20 + kernel)
    coords = _with_batch(idx, origin=-4)
    manager = CoordinateManager()
    manager.register(coords, 1)
    manager.downsample(1, 2)
    coarse = manager.coords(2)
    coarse_idx = torch.div(coarse[:, 1:] + 4, 2, rounding_mode="floor")
    x, w = _leaves((coarse.shape[0], 3), (kernel**3, 3, 2), seed=4)
    kmap = manager.kernel_map(2, 1, kernel)
    out = sparse_conv(x, w, kmap, method=method)
    pad, extra = (1, 1) if kernel == 3 else (0, 0)
    dense = F.conv_transpose3d(
        _dense(coarse_idx, x, n // 2),
        _tr_weight(w, kernel),
        stride=2,
        padding=pad,
        output_padding=extra,
    )
    ref = _read(dense, idx)
    torch.testing.assert_close(out, ref, **TOL)

    probe = torch.randn_like(out)
    for got, want in zip(_grads(out, probe, x, w), _grads(ref, probe, x, w), strict=True):
        torch.testing.assert_close(got, want, **TOL)


def test_transposed_module_undoes_strides_onto_seen_sites() -> None:
    idx = _active_grid(8, 0.2, seed=5)
    x = SparseTensor(torch.randn(idx.shape[0], 2, dtype=DT), _with_batch(idx))
    down = SparseConv3d(2, 4, kernel_size=3, stride=2).double()
    up = SparseConvTranspose3d(4, 3, kernel_size=3, stride=2).double()
    mid = down(x)
    assert mid.stride == 2 and bool((mid.coords[:, 1:] % 2 == 0).all())
    back = up(mid)
    assert back.stride == 1 and back.coords is x.coords
    assert back.features.shape == (idx.shape[0], 3)
    with pytest.raises(ValueError, match="stride"):
        up(x)  # nothing finer than stride 1 has been seen


def test_stride_two_tensor_matches_rescaled_stride_one() -> None:
    """Offsets are in units of the input tensor stride (MinkowskiEngine semantics)."""
    idx = _active_grid(6, 0.3, seed=6)
    feats = torch.randn(idx.shape[0], 2, dtype=DT)
    conv = SparseConv3d(2, 3, kernel_size=3, stride=2).double()
    fine = conv(SparseTensor(feats, _with_batch(idx)))
    coarse = conv(SparseTensor(feats, _with_batch(idx * 2), stride=2))
    assert coarse.stride == 4
    torch.testing.assert_close(coarse.coords[:, 1:], fine.coords[:, 1:] * 2)
    torch.testing.assert_close(coarse.features, fine.features, **TOL)


@pytest.mark.parametrize("kernel", [3, 5])
def test_lookups_and_methods_agree(kernel: int) -> None:
    idx = _active_grid(9, 0.3, seed=7)
    coords = _with_batch(idx, origin=-5)
    offsets = kernel_offsets(kernel)
    grid = build_kernel_map(coords, coords, offsets, submanifold=True, lookup="grid")
    srt = build_kernel_map(coords, coords, offsets, submanifold=True, lookup="sorted")
    assert grid.segments == srt.segments
    assert torch.equal(grid.in_idx, srt.in_idx) and torch.equal(grid.out_idx, srt.out_idx)
    x = torch.randn(idx.shape[0], 8, dtype=DT)
    w = torch.randn(kernel**3, 8, 6, dtype=DT)
    torch.testing.assert_close(
        sparse_conv(x, w, grid, "pairs"), sparse_conv(x, w, srt, "dense"), **TOL
    )


def _two_clouds() -> tuple[torch.Tensor, torch.Tensor]:
    a = _active_grid(8, 0.25, seed=8)
    b = _active_grid(8, 0.25, seed=9) + 2  # overlapping coordinates, other batch index
    return a, b


def test_batch_independence() -> None:
    torch.manual_seed(0)
    a, b = _two_clouds()
    fa, fb = torch.randn(a.shape[0], 3, dtype=DT), torch.randn(b.shape[0], 3, dtype=DT)
    layers = [
        SparseConv3d(3, 4, kernel_size=5),
        SparseConv3d(4, 4, kernel_size=3, stride=2),
        SparseConvTranspose3d(4, 2, kernel_size=3, stride=2),
    ]
    layers = [layer.double() for layer in layers]

    def run(x: SparseTensor) -> torch.Tensor:
        down = layers[1](layers[0](x))
        return layers[2](down).features

    both = run(sparse_collate([a, b], [fa, fb]))
    torch.testing.assert_close(both[: a.shape[0]], run(SparseTensor(fa, _with_batch(a))), **TOL)
    torch.testing.assert_close(
        both[a.shape[0] :], run(SparseTensor(fb, _with_batch(b, batch=0))), **TOL
    )


def test_two_threads_match_one() -> None:
    idx = _active_grid(12, 0.3, seed=11)
    coords = _with_batch(idx)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(idx.shape[0], 32, generator=gen)
    w = torch.randn(27, 32, 64, generator=gen) / 30
    kmap = build_kernel_map(coords, coords, kernel_offsets(3), submanifold=True)
    before = torch.get_num_threads()
    results = {}
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            results[threads] = [sparse_conv(x, w, kmap, m) for m in METHODS]
    finally:
        torch.set_num_threads(before)
    for one, two in zip(results[1], results[2], strict=True):
        torch.testing.assert_close(one, two, atol=1e-6, rtol=1e-6)


def test_batch_norm_and_cat_keep_sites() -> None:
    idx = _active_grid(5, 0.5, seed=12)
    x = SparseTensor(torch.randn(idx.shape[0], 3), _with_batch(idx))
    y = SparseBatchNorm(3)(x)
    assert y.same_sites(x)
    torch.testing.assert_close(y.features.mean(0), torch.zeros(3), atol=1e-5, rtol=0)
    z = sparse_cat(x, y)
    assert z.features.shape == (idx.shape[0], 6) and z.same_sites(x)
    other = SparseTensor(torch.randn(idx.shape[0], 3), _with_batch(idx))
    with pytest.raises(ValueError, match="same coordinates"):
        sparse_cat(x, other)


def test_bad_coordinates_are_rejected() -> None:
    coords = torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]])
    with pytest.raises(ValueError, match="unique"):
        SparseTensor(torch.zeros(2, 1), coords)
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        SparseTensor(torch.zeros(2, 1), coords[:, 1:])
    with pytest.raises(ValueError, match="features"):
        SparseTensor(torch.zeros(3, 1), coords[:1])


def test_scratch_buffers_never_leak_into_results() -> None:
    """Temporaries are reused across calls and modes; outputs must not alias them."""
    idx = _active_grid(8, 0.3, seed=13)
    coords = _with_batch(idx)
    kmap = build_kernel_map(coords, coords, kernel_offsets(3), submanifold=True)
    x = torch.randn(idx.shape[0], 4)
    w = torch.randn(27, 4, 4)
    with torch.inference_mode():
        first = sparse_conv(x, w, kmap, "pairs")
        kept = first.clone()
        sparse_conv(torch.randn_like(x), w, kmap, "pairs")
    torch.testing.assert_close(first, kept, atol=0, rtol=0)
    x.requires_grad_()
    sparse_conv(x, w, kmap, "pairs").sum().backward()  # buffers made in inference mode work here
    assert x.grad is not None and torch.isfinite(x.grad).all()
