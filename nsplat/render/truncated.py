"""A deterministic truncated surface-splatting renderer (baseline), differentiable by autograd.

Same EWA kernel, per-pixel depth and front-to-back alpha compositing as the op (docs/method.md; uses
:func:`nsplat.ops.project`), but each kernel is **cut at ``cutoff`` standard deviations**
(Mahalanobis distance ``sqrt(dᵀΣ⁻¹d) > cutoff`` → zero) and every pixel composites **exactly all
points in range**, with no sampling. This is the gradient behaviour of DSS/2DGS-style rasterisers:
a point receives gradient only from pixels inside its cut-off ellipse (local gradients).

The compositing is the PyTorch model of the exact tiled renderer (:func:`nsplat.ops.tiled.splat_tiled_torch`):
every (pixel, point) pair in range, sorted by (pixel, depth, index), composited with a segmented
log-transmittance sum; autograd differentiates it. Memory is ``O(Σ_pixels #points in range)`` per camera.
"""
from __future__ import annotations

import torch

from nsplat.ops import SplatOutput, project
from nsplat.ops.tiled import splat_tiled_torch


def splat_truncated(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                    features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                    *, cutoff: float = 3.0, background: torch.Tensor | None = None, near: float = 0.01,
                    far: float = 1e10, lowpass: float = 1.0, backface_cull: bool = False) -> SplatOutput:
    """Render with kernels truncated at ``cutoff`` σ and exact compositing of the points in range.

    Args:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]`` (> 0), opacities ``[N]`` in [0,1],
        features ``[N,C]`` or ``[B,N,C]``, viewmats ``[B,4,4]`` (world→camera, OpenCV), Ks ``[B,3,3]``: as for
        the op. width, height: image size in pixels.
        cutoff: truncation radius in standard deviations of the screen-space kernel (> 0).
        background: ``[C]`` background (default zeros). near, far, lowpass, backface_cull: as for the op.

    Returns:
        :class:`~nsplat.ops.SplatOutput` with ``image [B,H,W,C]``, ``alpha``, ``depth`` ``[B,H,W,1]`` and
        ``means2d [B,N,2]``; ``total = indices = probs = None``.
    """
    if cutoff <= 0:
        raise ValueError(f"cutoff: expected > 0, got {cutoff}")
    if width < 1 or height < 1:
        raise ValueError(f"width/height: expected >= 1, got {width}x{height}")
    C = features.shape[-1]
    bg = background if background is not None else means.new_zeros(C)
    if bg.shape != (C,):
        raise ValueError(f"background: expected shape [{C}], got {list(bg.shape)}")
    proj = project(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass,
                   backface_cull=backface_cull)
    out = splat_tiled_torch(proj, features, Ks, width, height, cutoff2=cutoff * cutoff, background=bg)
    return SplatOutput(image=out.image, alpha=out.alpha, depth=out.depth, means2d=proj.means2d)
