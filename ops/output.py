"""The result object of :func:`nsplat.ops.splat`, :func:`nsplat.ops.splat_dense` and :func:`nsplat.ops.splat_tiled`."""
from __future__ import annotations

import dataclasses

import torch


@dataclasses.dataclass
class SplatOutput:
    """Rendered images and the per-pixel sample.

    Attributes:
        image: ``[B, H, W, C]`` composited features (background where nothing was sampled).
        alpha: ``[B, H, W, 1]`` accumulated opacity ``1 - T_end`` (additive mode: ``Σ α/π``).
        depth: ``[B, H, W, 1]`` expected depth ``Σ w_k d_k`` (camera z of the ray–plane hit).
        total: ``[B, H, W, 1]`` total size measure ``Λ(x) = Σ_k λ_k(x)``: exact for the dense
            renderer, the tree estimate ``Λ̂(x)`` for the sampled op (no gradient); ``None`` for
            :func:`nsplat.ops.splat_tiled`.
        indices: ``[B, H, W, samples]`` int32 point indices of the sample, front to back by
            per-pixel depth, ``-1`` for empty slots (``None`` for the dense renderer).
        probs: ``[B, H, W, samples]`` inclusion probabilities ``π_k(x)`` of the sampled points,
            ``0`` for empty slots (``None`` for the dense renderer).
        work: ``[B, H, W, 1]`` int32 number of exact kernel evaluations the sampler made per pixel.
        means2d: ``[B, N, 2]`` the points' projected screen means, in the autograd graph: after a backward
            (``means2d.retain_grad()``) their gradient is each camera's own screen-space gradient of the points.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    total: torch.Tensor | None = None
    indices: torch.Tensor | None = None
    probs: torch.Tensor | None = None
    work: torch.Tensor | None = None
    means2d: torch.Tensor | None = None

    @property
    def normalized_depth(self) -> torch.Tensor:
        """``[B, H, W, 1]`` depth divided by alpha (0 where alpha is 0)."""
        a = self.alpha
        return torch.where(a > 0, self.depth / a.clamp_min(1e-12), torch.zeros_like(a))
