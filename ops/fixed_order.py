"""Broadcasts whose backward sums in a fixed order: the building block of the deterministic projection.

PyTorch reduces a broadcast operand's gradient with ``sum``, and a ``sum`` (like a BLAS matmul or an
``einsum``) splits its work by the thread count and the CPU's vector width, so the rounding of the
result depends on both. :func:`expand_fixed` instead returns an explicit expansion whose backward is a
pairwise tree of element-wise additions whose shape depends only on the length of the reduced
dimension. IEEE-754 rounds each element-wise ``+``, ``*``, ``/`` and ``sqrt`` exactly, whatever the
vector width or thread, so a computation made only of element-wise operations on same-shape tensors
(the projection in ``ops/projection.py``) is bitwise reproducible across thread counts and across
ATen's CPU capabilities (``ATEN_CPU_CAPABILITY=default|avx2|avx512``).
"""
from __future__ import annotations

import torch


def tree_sum(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Sum of ``x`` over ``dim`` (kept as size 1) by pairwise halving: ``x[:h] + x[h:2h]``, the odd last
    slice carried to the next round. The order of the additions depends only on ``x.shape[dim]``."""
    n = x.shape[dim]
    if n == 0:
        return x.sum(dim, keepdim=True)
    while n > 1:
        half = n // 2
        pair = x.narrow(dim, 0, half) + x.narrow(dim, half, half)
        x = torch.cat([pair, x.narrow(dim, 2 * half, 1)], dim) if n % 2 else pair
        n = x.shape[dim]
    return x


class _ExpandFixed(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, dim: int, size: int) -> torch.Tensor:  # noqa: ANN001
        ctx.dim = dim
        shape = list(x.shape)
        shape.insert(dim, size)
        return x.unsqueeze(dim).expand(shape)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # noqa: ANN001, ANN205
        return tree_sum(grad, ctx.dim).squeeze(ctx.dim), None, None


def expand_fixed(x: torch.Tensor, dim: int, size: int) -> torch.Tensor:
    """``x`` with a new dimension ``dim`` of length ``size`` inserted (a stride-0 view);
    its gradient is reduced over ``dim`` by :func:`tree_sum` (fixed order)."""
    return _ExpandFixed.apply(x, dim, size)
