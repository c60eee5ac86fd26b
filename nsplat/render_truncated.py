"""A deterministic truncated surface-splatting renderer (baseline), differentiable by autograd.

Same EWA kernel, per-pixel depth and front-to-back alpha compositing as the op (docs/method.md; uses
:func:`nsplat.ops.project`), but each kernel is **cut at ``cutoff`` standard deviations**
(Mahalanobis distance ``sqrt(dᵀΣ⁻¹d) > cutoff`` → zero) and every pixel composites **exactly all
points in range**, with no sampling. This is the gradient behaviour of DSS/2DGS-style rasterisers:
a point receives gradient only from pixels inside its cut-off ellipse (local gradients).

Memory is bounded by processing the image in square tiles: for each tile the candidate points are
those whose cut-off bounding square (radius ``cutoff·sqrt(λ_max(Σ))``) overlaps the tile; a no-grad
pass finds, per pixel, the candidates actually in range and packs them into ``[P, K_max]``; only that
packed set is evaluated with autograd. Peak autograd memory is ``O(Σ_pixels #points in range)``.
"""
from __future__ import annotations

import torch

from nsplat.ops import SplatOutput, project
from nsplat.ops.projection import ALPHA_MAX, PARALLEL_COS, pixel_rays


def _pixel_grid(x0: int, x1: int, y0: int, y1: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``[P,2]`` pixel centres ``(u, v)`` of the tile ``[x0,x1) × [y0,y1)``, row-major."""
    v, u = torch.meshgrid(torch.arange(y0, y1, dtype=dtype, device=device) + 0.5,
                          torch.arange(x0, x1, dtype=dtype, device=device) + 0.5, indexing="ij")
    return torch.stack([u, v], dim=-1).reshape(-1, 2)


def _quad(pix: torch.Tensor, mu: torch.Tensor, conic: torch.Tensor) -> torch.Tensor:
    """Mahalanobis ``dᵀΣ⁻¹d`` for pixels ``pix [P,(1),2]`` and splats ``mu [...,2]``, ``conic [...,3]``."""
    d = pix - mu
    dx, dy = d[..., 0], d[..., 1]
    return conic[..., 0] * dx * dx + 2.0 * conic[..., 1] * dx * dy + conic[..., 2] * dy * dy


def splat_truncated(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                    features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                    *, cutoff: float = 3.0, background: torch.Tensor | None = None, near: float = 0.01,
                    far: float = 1e10, lowpass: float = 1.0, backface_cull: bool = False,
                    tile: int = 16) -> SplatOutput:
    """Render with kernels truncated at ``cutoff`` σ and exact compositing of the points in range.

    Args:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]`` (> 0), opacities ``[N]`` in [0,1],
        features ``[N,C]``, viewmats ``[B,4,4]`` (world→camera, OpenCV), Ks ``[B,3,3]``: as for the op.
        width, height: image size in pixels.
        cutoff: truncation radius in standard deviations of the screen-space kernel (> 0).
        background: ``[C]`` background (default zeros). near, far, lowpass, backface_cull: as for the op.
        tile: tile edge in pixels (memory/speed trade-off; results do not depend on it).

    Returns:
        :class:`~nsplat.ops.SplatOutput` with ``image [B,H,W,C]``, ``alpha``, ``depth``, ``total``
        (``Σ α`` of the points in range, no gradient) ``[B,H,W,1]``; ``indices = probs = None``.
    """
    if cutoff <= 0:
        raise ValueError(f"cutoff: expected > 0, got {cutoff}")
    if tile < 1:
        raise ValueError(f"tile: expected >= 1, got {tile}")
    if width < 1 or height < 1:
        raise ValueError(f"width/height: expected >= 1, got {width}x{height}")
    C = features.shape[1]
    B = viewmats.shape[0]
    bg = background if background is not None else means.new_zeros(C)
    if bg.shape != (C,):
        raise ValueError(f"background: expected shape [{C}], got {list(bg.shape)}")
    proj = project(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass,
                   backface_cull=backface_cull)
    rays_all = pixel_rays(Ks, width, height)                       # [B,H,W,3]
    radius = cutoff * proj.sigma2.sqrt()                           # [B,N] px
    c2 = cutoff * cutoff
    images, alphas, depths, totals = [], [], [], []
    for b in range(B):
        mu_b, con_b, amp_b = proj.means2d[b], proj.conics[b], proj.amps[b]
        ncam_b, off_b, z_b = proj.normals_cam[b], proj.plane_offsets[b], proj.depths[b]
        with torch.no_grad():
            valid = proj.valid[b] & (amp_b > 0)
            lo = (mu_b - radius[b][:, None]).detach()
            hi = (mu_b + radius[b][:, None]).detach()
        rows_img, rows_a, rows_d, rows_t = [], [], [], []
        for y0 in range(0, height, tile):
            y1 = min(height, y0 + tile)
            cols_img, cols_a, cols_d, cols_t = [], [], [], []
            for x0 in range(0, width, tile):
                x1 = min(width, x0 + tile)
                out = _render_tile(x0, x1, y0, y1, valid, lo, hi, mu_b, con_b, amp_b, ncam_b, off_b, z_b,
                                   rays_all[b, y0:y1, x0:x1].reshape(-1, 3), features, bg, c2)
                shape = (y1 - y0, x1 - x0)
                cols_img.append(out[0].reshape(*shape, C))
                cols_a.append(out[1].reshape(*shape, 1))
                cols_d.append(out[2].reshape(*shape, 1))
                cols_t.append(out[3].reshape(*shape, 1))
            rows_img.append(torch.cat(cols_img, 1))
            rows_a.append(torch.cat(cols_a, 1))
            rows_d.append(torch.cat(cols_d, 1))
            rows_t.append(torch.cat(cols_t, 1))
        images.append(torch.cat(rows_img, 0))
        alphas.append(torch.cat(rows_a, 0))
        depths.append(torch.cat(rows_d, 0))
        totals.append(torch.cat(rows_t, 0))
    return SplatOutput(image=torch.stack(images), alpha=torch.stack(alphas), depth=torch.stack(depths),
                       total=torch.stack(totals), means2d=proj.means2d)


def _render_tile(x0: int, x1: int, y0: int, y1: int, valid: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                 mu: torch.Tensor, conic: torch.Tensor, amp: torch.Tensor, ncam: torch.Tensor, offset: torch.Tensor,
                 zc: torch.Tensor, rays: torch.Tensor, features: torch.Tensor, bg: torch.Tensor,
                 c2: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite one tile; returns ``(image [P,C], alpha [P,1], depth [P,1], total [P,1])``."""
    dtype, device = mu.dtype, mu.device
    pix = _pixel_grid(x0, x1, y0, y1, dtype, device)               # [P,2]
    P, C = pix.shape[0], features.shape[1]
    with torch.no_grad():
        # Candidate points: cut-off square overlaps the tile's pixel centres.
        cand = valid & (hi[:, 0] >= x0 + 0.5) & (lo[:, 0] <= x1 - 0.5) & (hi[:, 1] >= y0 + 0.5) & (lo[:, 1] <= y1 - 0.5)
        cidx = cand.nonzero().squeeze(1)
        if cidx.numel() > 0:
            inside = _quad(pix[:, None, :], mu[cidx][None], conic[cidx][None]) <= c2   # [P,M]
            kmax = int(inside.sum(1).max())
        else:
            kmax = 0
    if kmax == 0:
        zero = pix.new_zeros(P, 1)
        return bg.expand(P, C), zero, zero, zero
    with torch.no_grad():
        order = torch.argsort((~inside).to(torch.int8), dim=1, stable=True)[:, :kmax]
        in_range = torch.gather(inside, 1, order)                  # [P,K]
        idx = cidx[order]                                          # [P,K] point ids
    q = _quad(pix[:, None, :], mu[idx], conic[idx])                # [P,K]
    alpha = torch.clamp(amp[idx] * torch.exp(-0.5 * q), max=ALPHA_MAX) * in_range
    # Per-pixel depth: ray-plane intersection (centre depth when the ray is nearly parallel).
    n = ncam[idx]                                                  # [P,K,3]
    dot = (rays[:, None, :] * n).sum(-1)
    t = offset[idx] / torch.where(dot == 0, torch.ones_like(dot), dot)
    use_plane = (dot.abs() >= PARALLEL_COS * rays.norm(dim=-1, keepdim=True)) & (t > 0)
    depth = torch.where(use_plane, t, zc[idx])
    # Out-of-range slots sort last and have alpha 0.
    sort_key = torch.where(in_range, depth.detach(), torch.full_like(depth, float("inf")))
    order2 = torch.argsort(sort_key, dim=1, stable=True)
    a = torch.gather(alpha, 1, order2)
    d = torch.gather(depth, 1, order2)
    trans = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), 1.0 - a], dim=1), dim=1)
    w = a * trans[:, :-1]
    t_end = trans[:, -1:]
    f = features[torch.gather(idx, 1, order2)]                     # [P,K,C]
    image = torch.einsum("pk,pkc->pc", w, f) + t_end * bg
    return image, 1.0 - t_end, (w * d).sum(-1, keepdim=True), alpha.detach().sum(-1, keepdim=True)
