"""A differentiable 3D Gaussian splatting rasteriser in plain PyTorch (CPU or GPU), for fitting an export's
Gaussians to nsplat's renders (:mod:`nsplat.gaussians.fit`).

It forms the image as 3DGS's rasteriser does (Kerbl et al. 2023; the same rules as the test suite's independent
reference, ``tests/gs_reference.py``, which checks it): EWA projection ``Σ' = J W Σ Wᵀ Jᵀ + 0.3·I`` with ``t_x/t_z``,
``t_y/t_z`` clamped to 1.3× the half field of view; ``α = min(0.999, o·exp(−½ dᵀΣ'⁻¹d))`` at pixel centres,
``o`` times Mip-Splatting's ``sqrt(det(Σ' − 0.3 I) / det Σ')`` when ``antialiased``; alphas below 1/255
skipped; Gaussians in centre-depth order, front to back, each pixel stopping before the Gaussian that would take
its transmittance below 1e-4; a Gaussian reaches only the 16×16 tiles its ``3σ`` square touches.

Instead of tiles it works on (pixel, Gaussian) pairs: each Gaussian lists the pixels of its footprint (the
pixels of its tiles inside the bounding box of ``α ≥ 1/255``), the pairs are sorted by pixel (stably, after the
Gaussians were sorted by depth), and the transmittance is an exclusive cumulative sum of ``log(1 − α)`` per
pixel segment (float64). Memory and time grow with the number of pairs (a few per pixel per layer of depth).
"""
from __future__ import annotations

import math

import torch

#: 3DGS's screen dilation (px²).
EPS2D = 0.3
#: 3DGS's tile size (px).
TILE = 16
#: Alphas below this are skipped.
MIN_ALPHA = 1.0 / 255.0
#: A pixel stops before the Gaussian that would take its transmittance below this.
MIN_TRANSMITTANCE = 1e-4


def project(means: torch.Tensor, covs: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int,
            height: int, *, near: float = 0.01) -> tuple[torch.Tensor, ...]:
    """Camera depth ``[N]``, screen centre ``[N,2]``, screen covariance before the dilation ``[N,2,2]`` and a
    visibility mask ``[N]`` (in front of ``near``) of Gaussians ``means [N,3]``, ``covs [N,3,3]`` for one camera
    (``viewmat [4,4]`` OpenCV world→camera, ``K [3,3]``)."""
    Wr, w = viewmat[:3, :3].to(means), viewmat[:3, 3].to(means)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    t = means @ Wr.T + w
    tz = t[:, 2].clamp_min(near)
    lim_x, lim_y = 1.3 * (0.5 * width / fx), 1.3 * (0.5 * height / fy)
    tx = torch.maximum(torch.minimum(t[:, 0] / tz, lim_x), -lim_x) * tz
    ty = torch.maximum(torch.minimum(t[:, 1] / tz, lim_y), -lim_y) * tz
    zero = torch.zeros_like(tz)
    J = torch.stack([torch.stack([fx / tz, zero, -fx * tx / tz**2], -1),
                     torch.stack([zero, fy / tz, -fy * ty / tz**2], -1)], 1)    # [N,2,3]
    T = J @ Wr
    cov2 = T @ covs @ T.transpose(1, 2)
    mu = torch.stack([fx * t[:, 0] / tz + cx, fy * t[:, 1] / tz + cy], -1)
    return t[:, 2], mu, cov2, t[:, 2] > near


def _footprints(mu: torch.Tensor, cov: torch.Tensor, opac: torch.Tensor, width: int,
                height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Inclusive pixel rectangles ``lo [N,2]``, ``hi [N,2]`` (x, y) of Gaussians with dilated screen covariance
    ``cov [N,2,2]``: the pixels of the tiles their ``3σ`` square touches that lie inside the bounding box of
    ``o·exp(−½ dᵀΣ'⁻¹d) ≥ 1/255`` (empty where ``hi < lo``)."""
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    mid = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    radius = torch.ceil(3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))))
    q = 2.0 * torch.log(torch.clamp_min(opac / MIN_ALPHA, 1.0))              # dᵀΣ'⁻¹d where α = 1/255
    half = torch.sqrt(q[:, None] * torch.stack([cov[:, 0, 0], cov[:, 1, 1]], -1))
    size = torch.tensor([width, height], dtype=mu.dtype)
    tiles = torch.ceil(size / TILE)
    t_lo = torch.floor((mu - radius[:, None]) / TILE).clamp(min=torch.zeros_like(tiles), max=tiles)
    t_hi = torch.floor((mu + radius[:, None] + TILE - 1) / TILE).clamp(min=torch.zeros_like(tiles), max=tiles)
    lo = torch.maximum(torch.ceil(mu - half - 0.5), t_lo * TILE)
    hi = torch.minimum(torch.minimum(torch.floor(mu + half - 0.5), t_hi * TILE - 1), size - 1)
    inside = ((mu + radius[:, None] > 0) & (mu - radius[:, None] < size)).all(-1)    # the rasteriser's culling
    return lo.long(), torch.where(inside[:, None], hi, lo - 1).long()


def _alpha(a: torch.Tensor, px: torch.Tensor, py: torch.Tensor, alpha_clamp: float) -> torch.Tensor:
    """Alphas ``[P]`` of pairs with their Gaussian's ``a [P,9]`` (centre 2, conic 3, opacity 1, colour 3) at pixels
    ``px, py [P]`` (centres at +½)."""
    dx, dy = px.to(a) + 0.5 - a[:, 0], py.to(a) + 0.5 - a[:, 1]
    power = -0.5 * (a[:, 2] * dx * dx + a[:, 4] * dy * dy) - a[:, 3] * dx * dy
    return torch.clamp_max(a[:, 5] * torch.exp(power), alpha_clamp)


def rasterize(means: torch.Tensor, covs: torch.Tensor, opacities: torch.Tensor, colours: torch.Tensor,
              viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, background: torch.Tensor, *,
              antialiased: bool = False, near: float = 0.01, alpha_clamp: float = 0.999) -> torch.Tensor:
    """Render Gaussians into one camera (module docstring), differentiably in every input tensor.

    Args:
        means ``[N,3]``, covs ``[N,3,3]`` world covariances, opacities ``[N]`` in [0, 1], colours ``[N,3]`` (this
        camera's colour of each Gaussian). viewmat ``[4,4]`` OpenCV world→camera, K ``[3,3]`` pixels.
        background ``[3]``. antialiased: Mip-Splatting's opacity compensation. alpha_clamp: 0.999 (gsplat).

    Returns:
        The image ``[H,W,3]`` (dtype of ``means``).
    """
    depth, mu, cov0, vis = project(means, covs, viewmat, K, width, height, near=near)
    cov = cov0 + EPS2D * torch.eye(2, dtype=cov0.dtype, device=cov0.device)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    vis = vis & (det > 0)
    det = torch.where(vis, det, torch.ones_like(det))
    opac = opacities.to(means)
    if antialiased:
        det0 = cov0[:, 0, 0] * cov0[:, 1, 1] - cov0[:, 0, 1] ** 2
        opac = opac * torch.sqrt(torch.clamp_min(det0, 0.0) / det)
    with torch.no_grad():
        lo, hi = _footprints(mu.detach(), cov.detach(), opac.detach(), width, height)
        extent = (hi - lo + 1).clamp_min(0)
        count = torch.where(vis, extent[:, 0] * extent[:, 1], 0)
        order = torch.argsort(torch.where(vis, depth.detach(), math.inf), stable=True)
        order = order[count[order] > 0]                                      # nearest first
        gid = torch.repeat_interleave(order, count[order])
        start = torch.cumsum(count[order], 0) - count[order]
        off = torch.arange(gid.shape[0], device=gid.device) - torch.repeat_interleave(start, count[order])
        px = lo[gid, 0] + off % extent[gid, 0]
        py = lo[gid, 1] + off // extent[gid, 0]
    conic = torch.stack([cov[:, 1, 1], -cov[:, 0, 1], cov[:, 0, 0]], -1) / det[:, None]
    attrs = torch.cat([mu, conic, opac[:, None], colours.to(means)], 1)      # [N,9]: one gather per pair
    with torch.no_grad():
        keep = torch.nonzero(_alpha(attrs.index_select(0, gid), px, py, alpha_clamp) >= MIN_ALPHA)[:, 0]
        pixel, perm = torch.sort((py * width + px)[keep], stable=True)     # per pixel, still nearest first
        keep = keep[perm]
        gid, px, py = gid[keep], px[keep], py[keep]
    a = attrs.index_select(0, gid)
    alpha = _alpha(a, px, py, alpha_clamp)
    log_t = torch.log1p(-alpha.double())
    csum = torch.cumsum(log_t, 0)
    with torch.no_grad():
        first = torch.ones_like(pixel, dtype=torch.bool)
        first[1:] = pixel[1:] != pixel[:-1]
        seg_start = torch.cummax(torch.where(first, torch.arange(pixel.shape[0], device=pixel.device), 0), 0).values
    before = csum - log_t                                                    # Σ log(1 − α) of all earlier pairs
    trans_log = before - before.index_select(0, seg_start)                   # exclusive, within the pixel
    with torch.no_grad():
        used = (trans_log + log_t) >= math.log(MIN_TRANSMITTANCE)
    weight = (alpha * torch.exp(trans_log).to(alpha) * used)[:, None]
    P = width * height
    image = torch.zeros(P, 3, dtype=means.dtype, device=means.device).index_add(0, pixel, weight * a[:, 6:9])
    t_end = torch.exp(torch.zeros(P, dtype=torch.float64, device=means.device).index_add(0, pixel, log_t * used))
    image = image + t_end.to(means)[:, None] * background.to(means)
    return image.reshape(height, width, 3)
