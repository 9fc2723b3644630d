"""Pure-PyTorch sparse convolution layers with MinkowskiEngine semantics: submanifold
convolution (outputs on the input sites), strided convolution (outputs on the unique
``floor(c / 2s) * 2s`` sites, offsets in units of the input stride), transposed convolution back
onto the finer sites seen on the way down, batch norm over active sites, ReLU and channel
concatenation. A convolution is either one gather of all (input, offset) pairs, one matmul per
non-empty offset and one ``index_add_`` scatter ("pairs", exact work), or one im2col gather and a
single matmul ("dense", for thin inputs such as the occupancy channel); a custom autograd function
recomputes the gathers in the backward pass instead of storing them.
"""

from __future__ import annotations

import math
import threading

import torch
from torch import Tensor, nn
from torch.autograd import Function
from torch.autograd.function import FunctionCtx, once_differentiable

from catalign.features.kernel_map import KernelMap
from catalign.features.sparse_tensor import CoordinateManager, SparseTensor

__all__ = [
    "CoordinateManager",
    "SparseBatchNorm",
    "SparseConv3d",
    "SparseConvTranspose3d",
    "SparseTensor",
    "sparse_cat",
    "sparse_conv",
    "sparse_relu",
]


class _Scratch(threading.local):
    """Per-thread reusable buffers for the large temporaries (gathered rows, products, im2col).

    They are several times the size of the features; allocating them afresh in every layer costs
    page faults that, on small VMs, rival the matmuls. Nothing that escapes a call lives here.
    """

    limit = 1 << 22  # elements per slot; bigger temporaries are allocated normally

    def __init__(self) -> None:
        self.buffers: dict[tuple[str, torch.dtype, torch.device], Tensor] = {}

    def get(self, slot: str, rows: int, cols: int, like: Tensor) -> Tensor:
        numel = rows * cols
        if numel > self.limit:
            return like.new_empty(rows, cols)
        key = (slot, like.dtype, like.device)
        buf = self.buffers.get(key)
        if buf is None or buf.numel() < numel:
            with torch.inference_mode(False):  # usable both in and outside inference mode
                buf = torch.empty(min(2 * numel, self.limit), dtype=like.dtype, device=like.device)
            self.buffers[key] = buf
        return buf[:numel].view(rows, cols)


_scratch = _Scratch()


def _pairs_forward(x: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
    """``out[j] = sum over pairs (i, j, k) of x[i] @ weight[k]``: gather, matmul per k, scatter.

    Exact work (only real pairs); best when the kernel is sparsely filled or channels are wide.
    """
    c_out = weight.shape[2]
    if kmap.identity_offset is not None:
        out = torch.mm(x, weight[kmap.identity_offset])
    else:
        out = x.new_zeros(kmap.n_out, c_out)
    n_pairs = kmap.in_idx.numel()
    if n_pairs:
        gathered = _scratch.get("gather", n_pairs, x.shape[1], x)
        torch.index_select(x, 0, kmap.in_idx, out=gathered)
        products = _scratch.get("product", n_pairs, c_out, x)
        weights = weight.unbind(0)
        sizes = kmap.segment_sizes
        for k, rows, dst in zip(
            kmap.segment_offsets, gathered.split(sizes), products.split(sizes), strict=True
        ):
            torch.mm(rows, weights[k], out=dst)
        out.index_add_(0, kmap.out_idx, products)
    return out


def _im2col(x: Tensor, kmap: KernelMap) -> Tensor:
    """(n_out, K * C_in) matrix of gathered neighbour features, zeros where no neighbour."""
    padded = torch.cat([x, x.new_zeros(1, x.shape[1])])
    cols = _scratch.get("cols", kmap.n_out * kmap.kernel_volume, x.shape[1], x)
    torch.index_select(padded, 0, kmap.gather_table.view(-1), out=cols)
    return cols.view(kmap.n_out, -1)


def _dense_forward(x: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
    """The same sum as one gather and one big matmul over all K offsets (im2col).

    Does K / fill more multiply-adds than the pair form but in a single efficient GEMM with no
    scatter and no Python loop; best for few input channels or densely filled kernels.
    """
    return torch.mm(_im2col(x, kmap), weight.reshape(-1, weight.shape[2]))


def _use_dense(kmap: KernelMap, c_in: int) -> bool:
    """im2col wins for thin inputs or nearly full kernels (measured on an AMD EPYC, FCGF sizes)."""
    dense_rows = kmap.n_out * kmap.kernel_volume
    return c_in * kmap.kernel_volume <= 256 or kmap.n_pairs >= 0.75 * dense_rows


def _conv(x: Tensor, weight: Tensor, kmap: KernelMap, method: str) -> Tensor:
    if method == "auto":
        method = "dense" if _use_dense(kmap, x.shape[1]) else "pairs"
    if method == "dense":
        return _dense_forward(x, weight, kmap)
    if method == "pairs":
        return _pairs_forward(x, weight, kmap)
    raise ValueError(f"unknown sparse convolution method {method!r}")


class _SparseConvFunction(Function):
    """Sparse convolution with a hand-written backward that recomputes gathers, never storing them.

    The input gradient is the transposed convolution of the output gradient with W[k]^T.
    """

    @staticmethod
    def forward(
        ctx: FunctionCtx, x: Tensor, weight: Tensor, kmap: KernelMap, method: str
    ) -> Tensor:
        ctx.save_for_backward(x, weight)
        ctx.kmap = kmap
        ctx.method = method
        return _conv(x, weight, kmap, method)

    @staticmethod
    @once_differentiable
    def backward(
        ctx: FunctionCtx, grad_out: Tensor
    ) -> tuple[Tensor | None, Tensor | None, None, None]:
        x, weight = ctx.saved_tensors
        kmap: KernelMap = ctx.kmap
        grad_out = grad_out.contiguous()
        grad_x = grad_w = None
        if ctx.needs_input_grad[0]:
            weight_t = weight.transpose(1, 2).contiguous()
            grad_x = _conv(grad_out, weight_t, kmap.transposed, ctx.method)
        if ctx.needs_input_grad[1]:
            method = ctx.method
            if method == "auto":
                method = "dense" if _use_dense(kmap, x.shape[1]) else "pairs"
            if method == "dense":
                grad_w = torch.mm(_im2col(x, kmap).t(), grad_out).view_as(weight)
            else:
                grad_w = torch.zeros_like(weight)
                if kmap.identity_offset is not None:
                    torch.mm(x.t(), grad_out, out=grad_w[kmap.identity_offset])
                n_pairs = kmap.in_idx.numel()
                if n_pairs:
                    x_pairs = _scratch.get("gather", n_pairs, x.shape[1], x)
                    torch.index_select(x, 0, kmap.in_idx, out=x_pairs)
                    g_pairs = _scratch.get("product", n_pairs, grad_out.shape[1], grad_out)
                    torch.index_select(grad_out, 0, kmap.out_idx, out=g_pairs)
                    grads = grad_w.unbind(0)
                    sizes = kmap.segment_sizes
                    for k, xs, gs in zip(
                        kmap.segment_offsets,
                        x_pairs.split(sizes),
                        g_pairs.split(sizes),
                        strict=True,
                    ):
                        torch.mm(xs.t(), gs, out=grads[k])
        return grad_x, grad_w, None, None


def sparse_conv(features: Tensor, weight: Tensor, kmap: KernelMap, method: str = "auto") -> Tensor:
    """Apply a (K, C_in, C_out) kernel along ``kmap`` to (N_in, C_in) features.

    ``method`` picks the kernel: "pairs" (gather, matmul per offset, scatter), "dense" (im2col,
    one matmul) or "auto" (a cost model); all give the same result up to rounding.
    """
    if weight.shape[0] != kmap.kernel_volume or features.shape[0] != kmap.n_in:
        raise ValueError("weight or features do not match the kernel map")
    if features.dtype != weight.dtype:
        raise ValueError(f"features are {features.dtype} but weights are {weight.dtype}")
    features = features.contiguous()
    if torch.is_grad_enabled() and (features.requires_grad or weight.requires_grad):
        return _SparseConvFunction.apply(features, weight, kmap, method)
    return _conv(features, weight, kmap, method)  # inference: no autograd bookkeeping


class _SparseConvBase(nn.Module):
    """Weights stored as (K, C_in, C_out) so each offset's slice is a ready matmul operand."""

    def __init__(
        self, in_channels: int, out_channels: int, kernel_size: int, stride: int, bias: bool
    ) -> None:
        super().__init__()
        if stride < 1 or kernel_size < 1:
            raise ValueError("kernel_size and stride must be >= 1")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.stride = stride
        volume = kernel_size**3
        self.weight = nn.Parameter(torch.empty(volume, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # Same bound as torch's Conv3d default (kaiming_uniform with a=sqrt(5)).
        bound = 1.0 / math.sqrt(self.in_channels * self.weight.shape[0])
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def _finish(self, x: SparseTensor, features: Tensor, stride: int) -> SparseTensor:
        if self.bias is not None:
            features = features + self.bias
        return SparseTensor.on(features, x.manager, stride)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, "
            f"stride={self.stride}, bias={self.bias is not None}"
        )


class SparseConv3d(_SparseConvBase):
    """Submanifold (stride 1) or strided convolution, ``MinkowskiConvolution`` semantics."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        stride: int = 1,
        bias: bool = False,
    ) -> None:
        super().__init__(in_channels, out_channels, kernel_size, stride, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        out_stride = x.manager.downsample(x.stride, self.stride) if self.stride > 1 else x.stride
        if self.kernel_size == 1 and self.stride == 1:
            features = x.features @ self.weight[0]  # a 1x1x1 kernel is a plain linear layer
        else:
            kmap = x.manager.kernel_map(x.stride, out_stride, self.kernel_size)
            features = sparse_conv(x.features, self.weight, kmap)
        return self._finish(x, features, out_stride)


class SparseConvTranspose3d(_SparseConvBase):
    """Transposed convolution onto the finer sites the manager already holds (not generative)."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        stride: int = 2,
        bias: bool = False,
    ) -> None:
        super().__init__(in_channels, out_channels, kernel_size, stride, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.stride % self.stride:
            raise ValueError(f"cannot upsample stride {x.stride} by {self.stride}")
        out_stride = x.stride // self.stride
        kmap = x.manager.kernel_map(x.stride, out_stride, self.kernel_size)
        return self._finish(x, sparse_conv(x.features, self.weight, kmap), out_stride)


class SparseBatchNorm(nn.BatchNorm1d):
    """``BatchNorm1d`` over the active sites (rows of the feature matrix)."""

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.with_features(super().forward(x.features))


def sparse_relu(x: SparseTensor) -> SparseTensor:
    return x.with_features(torch.relu(x.features))


def sparse_cat(*tensors: SparseTensor) -> SparseTensor:
    """Concatenate channels of tensors on the same sites (``ME.cat``)."""
    first = tensors[0]
    if not all(first.same_sites(t) for t in tensors[1:]):
        raise ValueError("sparse_cat needs tensors on the same coordinates")
    return first.with_features(torch.cat([t.features for t in tensors], dim=1))
