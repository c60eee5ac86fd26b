"""Dense, exact PyTorch renderer (the oracle) and brute-force sequential Poisson sampling.

``splat_dense`` evaluates every point at every pixel (O(N·pixels)), sorts by per-pixel depth and
composites; it is differentiable by autograd and runs on any device. ``sps_bruteforce`` draws the
exact SPS sample of every pixel with the op's RNG. Both share the per-pixel model with the native
op (``size_measure``/``splat_depth`` below mirror ``csrc/core/ewa.h``).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .output import SplatOutput
from .projection import ALPHA_MAX, PARALLEL_COS, Projected, pixel_rays, project_torch
from .rng import uniforms
from .validation import check_backface_cull, check_dense_allocation, check_geometry, check_settings

#: The samplers' floor on a pixel's total size measure Lambda: below it a pixel gets no sample (its alpha is
#: below half an ulp of a float 1). ops/csrc/core/common.h: kMinTotal.
MIN_TOTAL = 2.0**-24


def pixel_centres(width: int, height: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``[H*W, 2]`` pixel centre coordinates ``(u, v) = (col + 0.5, row + 0.5)`` in row-major order."""
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                          torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    return torch.stack([u, v], dim=-1).reshape(-1, 2)


def splat_alpha(pix: torch.Tensor, means2d: torch.Tensor, conics: torch.Tensor,
                amps: torch.Tensor) -> torch.Tensor:
    """Alpha ``[P, N]`` of splats ``[N]`` at pixels ``pix [P,2]``: ``min(α_max, A·exp(-½dᵀΣ⁻¹d))``."""
    d = pix[:, None, :] - means2d[None, :, :]
    dx, dy = d[..., 0], d[..., 1]
    quad = conics[:, 0] * dx * dx + 2.0 * conics[:, 1] * dx * dy + conics[:, 2] * dy * dy
    return torch.clamp(amps * torch.exp(-0.5 * quad), max=ALPHA_MAX)


def splat_depth(rays: torch.Tensor, normals_cam: torch.Tensor, plane_offsets: torch.Tensor,
                depths: torch.Tensor) -> torch.Tensor:
    """Per-pixel depth ``[P, N]``: camera z where the pixel ray ``rays [P,3]`` (z = 1) meets each
    splat's tangent plane; the centre depth where the ray is within ``PARALLEL_COS`` of parallel
    to the plane or meets it behind the camera."""
    dot = rays @ normals_cam.T
    rnorm = rays.norm(dim=-1, keepdim=True)
    t = plane_offsets[None, :] / torch.where(dot == 0, torch.ones_like(dot), dot)
    use_plane = (dot.abs() >= PARALLEL_COS * rnorm) & (t > 0)
    return torch.where(use_plane, t, depths[None, :].expand_as(t))


def _composite_dense(alpha: torch.Tensor, depth: torch.Tensor, features: torch.Tensor,
                     background: torch.Tensor, composite: str) -> tuple[torch.Tensor, ...]:
    """Composite all points of ``P`` pixels: alpha/depth ``[P,N]``, features ``[N,C]``."""
    if composite == "additive":
        a_sum = alpha.sum(-1, keepdim=True)
        image = alpha @ features + (1.0 - a_sum) * background
        return image, a_sum, (alpha * depth).sum(-1, keepdim=True)
    depth_sorted, order = torch.sort(depth, dim=-1, stable=True)
    a = torch.gather(alpha, 1, order)
    trans = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), 1.0 - a], dim=1), dim=1)
    w = a * trans[:, :-1]
    t_end = trans[:, -1:]
    image = torch.einsum("pn,pnc->pc", w, features[order]) + t_end * background
    return image, 1.0 - t_end, (w * depth_sorted).sum(-1, keepdim=True)


def splat_dense(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                *, composite: str = "alpha", background: torch.Tensor | None = None, near: float = 0.01,
                far: float = 1e10, lowpass: float = 1.0, backface_cull: bool = False,
                max_chunk: int = 2**22) -> SplatOutput:
    """Exact surface splatting of all N points at every pixel (the oracle; O(N·H·W) time and memory).

    Same geometry, conventions and compositing as :func:`nsplat.ops.splat` (see its docstring), with
    every point evaluated at every pixel, no sampling and no floor. Differentiable by autograd.

    Args:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]``, opacities ``[N]``, features ``[N,C]`` or
        ``[B,N,C]``, viewmats ``[B,4,4]``, Ks ``[B,3,3]``: as in :func:`nsplat.ops.splat`.
        backface_cull: cull surfels facing away from each camera, as :func:`nsplat.ops.splat`.
        max_chunk: pixels × points × channels evaluated at once (bounds peak memory).

    Returns:
        :class:`SplatOutput` with ``image [B,H,W,C]``, ``alpha``, ``depth``, ``total [B,H,W,1]``
        and ``indices = probs = None``.
    """
    N, C, B = check_geometry(means, normals, scales, opacities, features, viewmats, Ks)
    check_settings(width=width, height=height, near=near, far=far, lowpass=lowpass, composite=composite,
                   background=background, C=C, dtype=means.dtype, device=means.device)
    bg = background if background is not None else means.new_zeros(C)
    check_backface_cull(backface_cull)
    grad = torch.is_grad_enabled() and any(isinstance(t, torch.Tensor) and t.requires_grad for t in
                                           (means, normals, scales, opacities, features, viewmats, Ks, background))
    check_dense_allocation(B=B, N=N, C=C, width=width, height=height, grad=grad, dtype=means.dtype,
                           device=means.device)
    # the pure-PyTorch projection: the oracle shares no native code with the op it checks
    proj = project_torch(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass,
                         backface_cull=backface_cull)
    pix = pixel_centres(width, height, means.dtype, means.device)
    rays = pixel_rays(Ks, width, height).reshape(B, -1, 3)
    chunk = max(1, max_chunk // max(1, N * (C + 4)))
    outs: list[list[torch.Tensor]] = [[], [], [], []]
    for b in range(B):
        per_cam: list[list[torch.Tensor]] = [[], [], [], []]
        for s in range(0, pix.shape[0], chunk):
            p = pix[s:s + chunk]
            alpha = splat_alpha(p, proj.means2d[b], proj.conics[b], proj.amps[b])
            depth = splat_depth(rays[b, s:s + chunk], proj.normals_cam[b], proj.plane_offsets[b], proj.depths[b])
            img, a, d = _composite_dense(alpha, depth, features if features.dim() == 2 else features[b], bg,
                                         composite)
            for lst, v in zip(per_cam, (img, a, d, alpha.sum(-1, keepdim=True).detach())):
                lst.append(v)
        for lst, pc in zip(outs, per_cam):
            lst.append(torch.cat(pc, 0).reshape(height, width, -1))
    image, alpha, depth, total = (torch.stack(o, 0) for o in outs)
    return SplatOutput(image=image, alpha=alpha, depth=depth, total=total, means2d=proj.means2d)


def size_measures(proj: Projected, camera: int, width: int, height: int) -> torch.Tensor:
    """Exact sampler size measures ``λ_k(x) = α_k(x)`` in float64: ``[H*W, N]`` (0 for culled points)."""
    pix = pixel_centres(width, height, torch.float64, proj.means2d.device)
    lam = splat_alpha(pix, proj.means2d[camera].double(), proj.conics[camera].double(),
                      proj.amps[camera].double())
    return lam * proj.valid[camera][None, :]


def sps_bruteforce(lam: torch.Tensor, samples: int, seed: int, camera: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact sequential Poisson sample per pixel from size measures ``lam [P, N]`` (float64).

    ``ξ_k = u_k / λ_k`` with the op's RNG; the sample is the ``samples`` points with the smallest
    ``ξ`` among those with ``λ > 0``. Returns ``(indices [P, samples]`` int64 sorted by ξ, ``-1``
    padded, ``keys [P, samples + 1])`` the sorted ``log ξ`` (``+inf`` padded), one extra key for
    detecting near-ties at the sample boundary.
    """
    P, N = lam.shape
    lam_np = lam.detach().cpu().numpy()
    u = uniforms(seed, camera, np.arange(P), np.arange(N))
    with np.errstate(divide="ignore"):
        keys = np.where(lam_np > 0, np.log(u) - np.log(lam_np), np.inf)
    order = np.argsort(keys, axis=1, kind="stable")
    k = min(samples + 1, N)
    sorted_keys = np.take_along_axis(keys, order[:, :k], axis=1)
    idx = np.where(np.isfinite(sorted_keys[:, :samples]), order[:, :min(samples, N)], -1)
    out_idx = np.full((P, samples), -1, dtype=np.int64)
    out_idx[:, :idx.shape[1]] = idx
    out_keys = np.full((P, samples + 1), np.inf)
    out_keys[:, :k] = sorted_keys
    return out_idx, out_keys


def pips_probabilities(lam: torch.Tensor, samples: int) -> torch.Tensor:
    """πps inclusion probabilities ``min(1, c·λ)`` with ``Σ π = min(samples, #{λ>0})``: ``[P, N]``."""
    lam = lam.double()
    P, N = lam.shape
    vals, _ = torch.sort(lam, dim=1, descending=True)
    out = torch.zeros_like(lam)
    for p in range(P):
        v = vals[p]
        nz = int((v > 0).sum())
        if nz <= samples:
            out[p] = (lam[p] > 0).double()
            continue
        rest = float(v.sum())
        c = math.inf
        for j in range(samples):
            cj = (samples - j) / rest
            if cj * float(v[j]) < 1.0:
                c = cj
                break
            rest -= float(v[j])
        out[p] = torch.clamp(c * lam[p], max=1.0) if math.isfinite(c) else (lam[p] > 0).double()
    return out


def sps_inclusion_probabilities(lam: np.ndarray, samples: int) -> np.ndarray:
    """Exact inclusion probabilities ``[N]`` of sequential Poisson sampling for size measures ``lam [N]``.

    ``P(k ∈ S) = ∫_0^{1/λ_k} λ_k · P(#{j≠k : ξ_j < t} < m) dt`` where ``P(ξ_j < t) = min(1, λ_j t)``.
    Between consecutive breakpoints ``1/λ_j`` the integrand is a polynomial of degree < N in ``t``,
    so Gauss–Legendre quadrature with ``⌈N/2⌉ + 1`` nodes per piece is exact up to rounding; the
    Poisson-binomial count is a dynamic programme truncated at ``m``.
    """
    lam = np.asarray(lam, dtype=np.float64)
    out = np.zeros_like(lam)
    idx = np.nonzero(lam > 0)[0]
    if len(idx) <= samples:
        out[idx] = 1.0
        return out
    lv = lam[idx]
    n = len(lv)
    xg, wg = np.polynomial.legendre.leggauss(n // 2 + 2)
    breaks = np.sort(1.0 / lv)
    for i in range(n):
        others = np.delete(lv, i)
        end = 1.0 / lv[i]
        edges = np.concatenate([[0.0], breaks[breaks < end], [end]])
        a, b = edges[:-1], edges[1:]
        keep = b > a
        a, b = a[keep], b[keep]
        t = (0.5 * (b - a)[:, None] * xg[None, :] + 0.5 * (a + b)[:, None]).reshape(-1)
        wt = (0.5 * (b - a)[:, None] * wg[None, :]).reshape(-1)
        p = np.minimum(1.0, t[:, None] * others[None, :])
        dp = np.zeros((len(t), samples))
        dp[:, 0] = 1.0
        for j in range(n - 1):
            pj = p[:, j:j + 1]
            shifted = np.concatenate([np.zeros((len(t), 1)), dp[:, :-1]], axis=1)
            dp = dp * (1.0 - pj) + shifted * pj
        out[idx[i]] = lv[i] * float((wt * dp.sum(axis=1)).sum())
    return out


def sps_expectation_weights(lam: torch.Tensor, samples: int) -> torch.Tensor:
    """``[P, N]`` ratios ``P_k(x) / π_k(x)`` of exact SPS inclusion to πps probabilities (0 where λ = 0).

    The expectation over SPS samples of any Horvitz–Thompson sum ``Σ_{k∈S} t_k / π_k`` is
    ``Σ_k (P_k / π_k) t_k``; with these weights the tests compute it exactly (the implied bias of using
    πps probabilities with SPS, Ohlsson 1998).
    """
    pips = pips_probabilities(lam, samples).numpy()
    out = np.zeros_like(pips)
    for p in range(lam.shape[0]):
        exact = sps_inclusion_probabilities(lam[p].numpy(), samples)
        nz = pips[p] > 0
        out[p, nz] = exact[nz] / pips[p, nz]
    return torch.from_numpy(out)
