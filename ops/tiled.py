"""Tiled render of every splat within reach: the dense oracle's image to a tolerance, at sparse cost.

:func:`splat_tiled` composites, at every pixel, every splat whose kernel there is at least ``tol`` of its peak
(Mahalanobis radius ``sqrt(2 ln(1/tol))``), sorted by per-pixel depth as :func:`nsplat.ops.splat_dense` sorts,
with the op's compositor. Its cost is pixels × (splats that reach a pixel) instead of pixels × points, and it
differs from the dense oracle by at most the cut tails: each splat's alpha changes by at most ``tol`` times its
amplitude, so an image with ``k`` splats in reach of a pixel moves by at most about ``k·tol`` times the feature
scale there. Made for ground-truth images (:mod:`nsplat.tasks.reconstruct_views`) and held-out renders; not
differentiable.

The CPU runs it natively (``csrc/cpu/tiled_cpu.cpp``: splats binned into 16×16 tiles, per-pixel sort); other
devices run :func:`splat_tiled_torch`, the same model in PyTorch (pairs of pixel and splat, one sort), which
the tests hold the native kernel to.
"""
from __future__ import annotations

import math

import torch

from .build import backend
from .output import SplatOutput
from .projection import ALPHA_MAX, PARALLEL_COS, Projected, pixel_rays, project
from .validation import check_geometry, check_settings
from .value_checks import value_checks


def cutoff2_of(tol: float) -> float:
    """The squared Mahalanobis radius ``2 ln(1/tol)`` where a kernel falls to ``tol`` of its peak.

    Raises:
        ValueError: ``tol`` is not in (0, 1).
    """
    if not isinstance(tol, (int, float)) or not 0.0 < float(tol) < 1.0:
        raise ValueError(f"tol: expected a float in (0, 1), got {tol!r}")
    return 2.0 * math.log(1.0 / float(tol))


@torch.no_grad()
def splat_tiled(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
                tol: float = 1e-7, background: torch.Tensor | None = None, near: float = 0.01, far: float = 1e10,
                lowpass: float = 1.0, backface_cull: bool = False) -> SplatOutput:
    """Alpha-composite every splat within ``tol`` of its peak at each pixel (no sampling, no gradient).

    Args:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]``, opacities ``[N]``, features ``[N,C]`` or ``[B,N,C]``,
        viewmats ``[B,4,4]``, Ks ``[B,3,3]``, width, height, background ``[C]``, near, far, lowpass,
        backface_cull: as for :func:`nsplat.ops.splat_dense` (alpha compositing).
        tol: relative kernel value below which a splat is left out of a pixel, in (0, 1).

    Returns:
        :class:`~nsplat.ops.SplatOutput` with ``image [B,H,W,C]``, ``alpha [B,H,W,1]``, ``depth [B,H,W,1]``.
    """
    cutoff2 = cutoff2_of(tol)
    with value_checks():
        _, C, _ = check_geometry(means, normals, scales, opacities, features, viewmats, Ks)
        check_settings(width=width, height=height, near=near, far=far, lowpass=lowpass, composite="alpha",
                       background=background, C=C, dtype=means.dtype, device=means.device)
    proj = project(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass,
                   backface_cull=backface_cull)
    bg = background if background is not None else features.new_zeros(C)
    if means.device.type != "cpu":
        return splat_tiled_torch(proj, features, Ks, width, height, cutoff2=cutoff2, background=bg)
    image, alpha, depth, _ = _native(proj, features, Ks, bg, width, height, tol, point_weights=False)
    return SplatOutput(image=image, alpha=alpha, depth=depth)


@torch.no_grad()
def point_weights_tiled(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                        viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *, tol: float = 1e-7,
                        near: float = 0.01, far: float = 1e10, lowpass: float = 1.0,
                        backface_cull: bool = False) -> torch.Tensor:
    """``[B,N]``: each splat's alpha-compositing weights ``w_k(x) = α_k(x)·T_k(x)`` summed over every pixel of each
    camera, with :func:`splat_tiled`'s model (every splat within ``tol`` of its peak, exact order): how much each
    point shows in each view, with no sampling (a point hidden behind a surface shows ``≈ 0``). CPU only (the
    arguments are moved there); arguments as for :func:`splat_tiled`."""
    cutoff2_of(tol)
    args = [t.detach().cpu() for t in (means, normals, scales, opacities, viewmats, Ks)]
    with value_checks():
        check_geometry(*args[:4], None, *args[4:])
        check_settings(width=width, height=height, near=near, far=far, lowpass=lowpass, composite="alpha",
                       background=None, C=1, dtype=args[0].dtype, device=args[0].device)
    proj = project(*args, near=near, far=far, lowpass=lowpass, backface_cull=backface_cull)
    ones = args[0].new_zeros(args[0].shape[0], 1)
    *_, weights = _native(proj, ones, args[5], args[0].new_zeros(1), width, height, tol, point_weights=True)
    return weights.to(means.device)


def _native(proj: Projected, features: torch.Tensor, Ks: torch.Tensor, bg: torch.Tensor, width: int, height: int,
            tol: float, *, point_weights: bool) -> list[torch.Tensor]:
    """The CPU kernel ``render_tiled``: ``[image, alpha, depth, weights]`` (``weights [B,N]`` or empty)."""
    return backend(torch.device("cpu")).render_tiled(
        proj.means2d.contiguous(), proj.conics.contiguous(), proj.amps.contiguous(), proj.sigma2.contiguous(),
        proj.normals_cam.contiguous(), proj.plane_offsets.contiguous(), proj.depths.contiguous(), Ks.contiguous(),
        features.contiguous(), bg.contiguous(), int(width), int(height), cutoff2_of(tol), float(tol) ** 2,
        bool(point_weights))


def splat_tiled_torch(proj: Projected, features: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
                      cutoff2: float, background: torch.Tensor) -> SplatOutput:
    """The model of :func:`splat_tiled` in PyTorch, on projected splats ``proj [B,N,...]``, features ``[N,C]`` or
    ``[B,N,C]``, ``Ks [B,3,3]`` and ``background [C]``: every (pixel, splat) pair in the splat's square of half-width
    ``sqrt(cutoff2·σ²_max)`` with ``q <= cutoff2``, sorted by (pixel, per-pixel depth, index), composited with a
    segmented log-transmittance sum."""
    B, C = proj.amps.shape[0], features.shape[-1]
    dtype, device = proj.means2d.dtype, proj.means2d.device
    rays_all = pixel_rays(Ks.to(dtype), width, height).reshape(B, -1, 3)
    images, alphas, depths = [], [], []
    for b in range(B):
        keep = (proj.valid[b] & (proj.amps[b] > 0)).nonzero().squeeze(1)
        mu, con = proj.means2d[b, keep], proj.conics[b, keep]
        half = (cutoff2 * proj.sigma2[b, keep]).sqrt()
        x0 = torch.ceil(mu[:, 0] - half - 0.5).clamp(min=0).long()
        x1 = torch.floor(mu[:, 0] + half - 0.5).clamp(max=width - 1).long()
        y0 = torch.ceil(mu[:, 1] - half - 0.5).clamp(min=0).long()
        y1 = torch.floor(mu[:, 1] + half - 0.5).clamp(max=height - 1).long()
        nx, ny = (x1 - x0 + 1).clamp(min=0), (y1 - y0 + 1).clamp(min=0)
        counts = nx * ny
        pid = torch.repeat_interleave(torch.arange(keep.numel(), device=device), counts)
        local = torch.arange(pid.numel(), device=device) - (torch.cumsum(counts, 0) - counts)[pid]
        px, py = x0[pid] + local % nx[pid], y0[pid] + local // nx[pid]
        dx, dy = px.to(dtype) + 0.5 - mu[pid, 0], py.to(dtype) + 0.5 - mu[pid, 1]
        c = con[pid]
        q = c[:, 0] * dx * dx + 2.0 * c[:, 1] * dx * dy + c[:, 2] * dy * dy
        inside = q <= cutoff2
        k, pix, q = keep[pid[inside]], (py * width + px)[inside], q[inside]
        a = torch.clamp(proj.amps[b, k] * torch.exp(-0.5 * q), max=ALPHA_MAX)
        ray = rays_all[b, pix]
        dot = (ray * proj.normals_cam[b, k]).sum(-1)
        t = proj.plane_offsets[b, k] / torch.where(dot == 0, torch.ones_like(dot), dot)
        on_plane = (dot.abs() >= PARALLEL_COS * ray.norm(dim=-1)) & (t > 0)
        d = torch.where(on_plane, t, proj.depths[b, k])
        by_depth = torch.sort(d, stable=True).indices                  # ties: pairs are in index order
        order = by_depth[torch.sort(pix[by_depth], stable=True).indices]
        a, d, pix, k = a[order], d[order], pix[order], k[order]
        log_t = torch.log1p(-a.double())
        before = torch.cumsum(log_t, 0) - log_t                        # exclusive prefix sum
        per_pixel = torch.bincount(pix, minlength=width * height)
        first = torch.cumsum(per_pixel, 0) - per_pixel
        w = (a.double() * torch.exp(before - before[first[pix]])).to(dtype)
        f = features[b] if features.dim() == 3 else features
        t_end = torch.exp(torch.zeros(width * height, dtype=torch.float64, device=device).index_add_(0, pix, log_t))
        image = torch.zeros(width * height, C, dtype=dtype, device=device).index_add_(0, pix, w[:, None] * f[k])
        image = image + t_end.to(dtype)[:, None] * background
        depth = torch.zeros(width * height, dtype=dtype, device=device).index_add_(0, pix, w * d)
        images.append(image.reshape(height, width, C))
        alphas.append((1.0 - t_end).to(dtype).reshape(height, width, 1))
        depths.append(depth.reshape(height, width, 1))
    return SplatOutput(image=torch.stack(images), alpha=torch.stack(alphas), depth=torch.stack(depths))
