"""The sampled splatting op: ``splat`` (project → sample → composite) and its stages.

Stages (each usable on its own, PyTorch3D style):
    :func:`nsplat.ops.project`  differentiable EWA projection (PyTorch autograd)
    :func:`sample`              per-pixel sequential Poisson sample over the radix tree (native, no grad)
    :func:`composite_sample`    compositing of a given sample with the estimator's backward (native)
"""
from __future__ import annotations

import torch

from .build import backend
from .output import SplatOutput
from .projection import Projected, project
from .validation import (COMPOSITES, ESTIMATORS, INCLUSIONS, check_composite_call, check_deterministic,
                         check_geometry, check_sample_call, check_sampling, check_settings, inclusion_for,
                         native_estimator)


def _native_inputs(proj: Projected) -> list[torch.Tensor]:
    return [t.contiguous() for t in (proj.means2d, proj.conics, proj.amps, proj.normals_cam,
                                     proj.plane_offsets, proj.depths)]


@torch.no_grad()
def sample(proj: Projected, Ks: torch.Tensor, width: int, height: int, *, samples: int = 40, eps: float = 0.01,
           seed: int = 0, hermite_order: int = 8, hermite_tol: float = 1e-3, inclusion: str = "threshold",
           stratified: bool = False) -> tuple[torch.Tensor, ...]:
    """Draw each pixel's SPS sample of ``samples`` points (docs/method.md "Sampling").

    Args:
        proj: projected surfels of ``B`` cameras (:func:`nsplat.ops.project`).
        Ks: ``[B,3,3]`` intrinsics (pixel rays for per-pixel depth ordering).
        samples: sample size ``m`` per pixel. eps: bound on the probability that a pixel's sample
            differs from the exact SPS sample. seed: RNG seed (``u`` is a hash of seed, camera, pixel,
            point). hermite_order: maximum Hermite order per dimension (0 disables expansions).
            hermite_tol: relative truncation bound a node's expansion must meet.
            inclusion: which π to return. "threshold" (default): ``π_k = min(1, λ_k·ξ_(m+1))`` with
            ``ξ_(m+1)`` the pixel's (m+1)-th smallest key ``u/λ`` — the exact probability of k's inclusion
            given the other points' draws (priority sampling), so Horvitz–Thompson sums weighted by
            ``1/π`` are exactly unbiased. "pips": the πps targets ``min(1, c·λ_k)`` with ``Σπ = m``,
            which SPS meets only approximately (a small bias at small m and skewed λ).
            stratified: False (default): independent uniforms per (camera, pixel, point). True: one
            uniform per (camera, point) shifted per pixel by a rank-1 lattice, ``u = frac(h_k + φ(x))``:
            every pixel's sample is still an exact SPS draw with the same marginals (so estimators stay
            unbiased), but a point's draws are stratified across neighbouring pixels.

    Returns:
        ``indices [B,H,W,m]`` int32 (front to back, -1 empty), ``probs [B,H,W,m]`` (π, 0 empty),
        ``total [B,H,W,1]`` (Λ̂; 0 below the floor), ``work [B,H,W,1]`` int32 exact kernel evaluations.
    """
    if inclusion not in INCLUSIONS:
        raise ValueError(f"inclusion: expected one of {INCLUSIONS}, got {inclusion!r}")
    check_sample_call(proj, Ks, width, height, samples=samples, eps=eps, seed=seed, hermite_order=hermite_order,
                      hermite_tol=hermite_tol, stratified=stratified)
    mu, con, amp, nrm, off, zc = _native_inputs(proj)
    sig2 = proj.sigma2.contiguous()
    return tuple(backend(mu.device).sample(mu, con, amp, sig2, nrm, off, zc, Ks.detach().contiguous(), width,
                                           height, samples, float(eps), seed, hermite_order, float(hermite_tol),
                                           INCLUSIONS.index(inclusion), bool(stratified)))


class _Composite(torch.autograd.Function):
    """Compositing of a fixed sample. Backward (deterministic): pass 1 per pixel, pass 2 per point in
    a fixed (point, camera, slot) order. Non-deterministic (CPU only): one pass per pixel scattering
    into the per-point buffers with atomics (``csrc/cpu/scatter_cpu.cpp``)."""

    @staticmethod
    def forward(ctx, mode: int, estimator: int, deterministic: bool, Ks: torch.Tensor, indices: torch.Tensor,
                probs: torch.Tensor, mu, con, amp, nrm, off, zc, feat, bg):  # noqa: ANN001 - autograd signature
        ops = backend(mu.device)
        args = [t.contiguous() for t in (mu, con, amp, nrm, off, zc)]
        Kc = Ks.detach().contiguous()
        image, alpha, depth = ops.composite_forward(*args, Kc, feat.contiguous(), bg.contiguous(), indices, probs, mode)
        ctx.save_for_backward(*args, Kc, feat, bg, indices, probs)
        ctx.mode, ctx.estimator, ctx.deterministic = mode, estimator, deterministic
        return image, alpha, depth

    @staticmethod
    def backward(ctx, g_img, g_alpha, g_depth):  # noqa: ANN001
        mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs = ctx.saved_tensors
        ops = backend(mu.device)
        B, H, W, m = indices.shape
        N = amp.shape[1]
        g_img = torch.zeros(B, H, W, feat.shape[1], dtype=mu.dtype, device=mu.device) if g_img is None else g_img
        g_alpha = torch.zeros(B, H, W, 1, dtype=mu.dtype, device=mu.device) if g_alpha is None else g_alpha
        g_depth = torch.zeros(B, H, W, 1, dtype=mu.dtype, device=mu.device) if g_depth is None else g_depth
        g_img, g_alpha, g_depth = g_img.contiguous(), g_alpha.contiguous(), g_depth.contiguous()
        params = (mu, con, amp, nrm, off, zc)
        if not ctx.deterministic and mu.device.type == "cpu":
            *grads, bgw = ops.composite_backward_scatter(*params, Ks, feat.contiguous(), bg.contiguous(), indices,
                                                         probs, ctx.mode, ctx.estimator, g_img, g_alpha, g_depth)
            return (None, None, None, None, None, None, *grads, (bgw * g_img).sum(dim=(0, 1, 2)))
        dalpha, wf, bgw = ops.composite_backward_pixels(*params, Ks, feat.contiguous(), bg.contiguous(), indices,
                                                        probs, ctx.mode, ctx.estimator, g_img, g_alpha, g_depth)
        entries, seg = _entries_by_point(indices, N)
        grads = ops.composite_backward_points(*params, Ks, entries, seg, dalpha, wf, g_img, g_depth, W, H,
                                              ctx.estimator)
        g_bg = (bgw * g_img).sum(dim=(0, 1, 2))
        return (None, None, None, None, None, None, *grads, g_bg)


def _entries_by_point(indices: torch.Tensor, N: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat slot ids of the filled slots of ``indices [B,H,W,m]`` grouped by point, keeping their
    (camera, pixel, slot) order within a point, and per-point segment offsets ``seg [N+1]`` (int64).

    A backend with a native stable counting sort (the CPU one) uses it: 8 bytes per filled slot + 8 per
    point. Otherwise (CUDA): a stable device sort of the int32 point ids, :func:`_entries_by_point_sorted`
    (positions, ids, sort indices and the gathered order: ≈ 28 bytes per filled slot at the peak)."""
    native = getattr(backend(indices.device), "entries_by_point", None)
    if native is not None:
        entries, seg = native(indices.contiguous(), N)
        return entries, seg
    return _entries_by_point_sorted(indices, N)


def _entries_by_point_sorted(indices: torch.Tensor, N: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_entries_by_point` by a stable device sort (any device; the reference for the native one)."""
    flat = indices.reshape(-1)
    pos = torch.nonzero(flat >= 0).squeeze(1)
    keys, order = torch.sort(flat.index_select(0, pos), stable=True)
    entries = pos.index_select(0, order)
    del pos, order
    seg = torch.zeros(N + 1, dtype=torch.long, device=indices.device)
    seg[1:] = torch.cumsum(torch.bincount(keys, minlength=N), 0)
    return entries, seg


def composite_sample(proj: Projected, features: torch.Tensor, Ks: torch.Tensor, indices: torch.Tensor,
              probs: torch.Tensor, *, background: torch.Tensor | None = None, composite: str = "alpha",
              estimator: str = "ht", deterministic: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite a given per-pixel sample; differentiable w.r.t. ``proj``, ``features`` and ``background``.

    Slots are blended in the given order (front to back; :func:`sample` orders them by per-pixel
    depth). The backward applies the estimator's weight to every sampled term: ``"ht"`` and ``"ht-pips"``
    1/π (with whatever π is given: the two differ only in which π :func:`sample` returns for them),
    ``"paper"`` 1/(π·|N_k|) with |N_k| the number of pixels of the camera where k was sampled,
    ``"sampled"`` 1. The per-pixel depth's dependence on ``Ks`` (through the pixel rays) is not
    differentiated; ``Ks`` gets its gradient through the projection.

    Args:
        proj: projected surfels ``[B,N,...]``. features: ``[N,C]``. Ks: ``[B,3,3]``.
        indices: ``[B,H,W,m]`` int32. probs: ``[B,H,W,m]`` inclusion probabilities (dtype of proj).
        background: ``[C]`` (zeros if None). composite: "alpha" | "additive".
        estimator: "ht" | "ht-pips" | "paper" | "sampled".
        deterministic: True (default): fixed-order backward, gradients bitwise identical across runs and
            thread counts. False: single-pass atomic-scatter backward on CPU (faster, equal up to
            rounding, summation order varies); on CUDA only the deterministic backward exists and
            ``False`` falls back to it.

    Returns:
        ``image [B,H,W,C]``, ``alpha [B,H,W,1]``, ``depth [B,H,W,1]``.
    """
    check_composite_call(proj, features, Ks, indices, probs, background, composite, estimator, deterministic)
    if composite not in COMPOSITES:
        raise ValueError(f"composite: expected one of {COMPOSITES}, got {composite!r}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
    check_deterministic(deterministic)
    if indices.dtype != torch.int32 or indices.dim() != 4:
        raise TypeError(f"indices: expected an int32 tensor [B,H,W,m], got {indices.dtype} {list(indices.shape)}")
    if probs.shape != indices.shape or probs.dtype != proj.means2d.dtype:
        raise ValueError(f"probs: expected shape {list(indices.shape)} and dtype {proj.means2d.dtype}, "
                         f"got {list(probs.shape)} {probs.dtype}")
    bg = background if background is not None else features.new_zeros(features.shape[1])
    return _Composite.apply(COMPOSITES.index(composite), native_estimator(estimator), deterministic, Ks,
                            indices.contiguous(),
                            probs.contiguous(), proj.means2d, proj.conics, proj.amps, proj.normals_cam,
                            proj.plane_offsets, proj.depths, features, bg)


def splat(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
          features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
          samples: int = 40, eps: float = 0.01, estimator: str = "ht", composite: str = "alpha",
          background: torch.Tensor | None = None, near: float = 0.01, far: float = 1e10, lowpass: float = 1.0,
          seed: int = 0, hermite_order: int = 8, hermite_tol: float = 1e-3, deterministic: bool = True,
          stratified: bool = False) -> SplatOutput:
    """Render surfel features by EWA surface splatting with per-pixel Poisson sampling (unbiased backward).

    For every camera and pixel, a sequential Poisson sample of ``samples`` points is drawn with size
    measure ``λ_k(x) = α_k(x)`` (untruncated kernels), sorted by per-pixel depth, composited, and
    backpropagated with the chosen estimator (docs/method.md).

    Conventions: OpenCV camera (x right, y down, z forward), ``viewmats`` world→camera, ``Ks`` in
    pixels, pixel centres at ``(col + 0.5, row + 0.5)``, images ``[B,H,W,C]``. Splat alpha is the EWA
    kernel scaled to unit peak, ``α = min(0.99, o·|det J|/sqrt(det Σ)·exp(-½dᵀΣ⁻¹d))`` with
    ``Σ = J Jᵀ + lowpass·I``; depth is the camera z of the ray–plane hit (centre depth near grazing).

    Args:
        means: ``[N,3]`` world positions. normals: ``[N,3]`` non-zero (normalised inside).
        scales: ``[N,2]`` > 0, tangent standard deviations (world units) along the normal's frame.
        opacities: ``[N]`` in [0, 1]. features: ``[N,C]`` any C >= 1 (RGB or learned, signed).
        viewmats: ``[B,4,4]``. Ks: ``[B,3,3]``. width, height: image size (>= 1).
        samples: per-pixel sample size m (>= 1). eps: probability bound that a pixel's sample differs
            from exact SPS (0 < eps <= 1).
        estimator: "ht" (default): Horvitz–Thompson weights 1/π with the exact conditional inclusion
            probabilities of priority sampling, ``π = min(1, λ·ξ_(m+1))``; with additive compositing
            the image and every gradient are exactly unbiased estimates of the dense ones (up to the
            ε-search and the documented floors). "ht-pips": 1/π with the πps targets (SPS meets them
            only approximately: biased at small m, lower variance). "paper": eq. 3 as printed
            (HT / |N_k|, πps). "sampled": plain gradient through the sample (biased). With alpha
            compositing no estimator is unbiased (the transmittance is a product over the sample).
        composite: "alpha" (front-to-back blending) or "additive" (HT-weighted sum, no occlusion).
        background: ``[C]`` differentiable background (zeros if None). near, far: clipping on the centre
            depth. lowpass: screen-space low-pass variance in px² (the paper's +I is 1). seed: RNG seed.
        hermite_order, hermite_tol: tree expansion order cap and relative truncation tolerance.
        deterministic: True (default) gives run-to-run and thread-count independent, bitwise identical
            gradients (fixed-order per-point gather). False selects the faster single-pass CPU backward
            that scatters with atomics (equal up to float rounding). CUDA has only the deterministic
            backward; ``False`` on CUDA tensors silently uses it.
        stratified: stratified uniforms across pixels (see :func:`sample`); off by default.

    Returns:
        :class:`SplatOutput`: ``image [B,H,W,C]``, ``alpha [B,H,W,1]``, ``depth [B,H,W,1]``,
        ``total [B,H,W,1]`` (Λ̂), ``indices [B,H,W,m]`` int32, ``probs [B,H,W,m]``, ``work [B,H,W,1]``.
    """
    N, C, B = check_geometry(means, normals, scales, opacities, features, viewmats, Ks)
    check_settings(width=width, height=height, near=near, far=far, lowpass=lowpass, composite=composite,
                   background=background, C=C, dtype=means.dtype, device=means.device)
    check_sampling(samples=samples, eps=eps, estimator=estimator, seed=seed, hermite_order=hermite_order,
                   hermite_tol=hermite_tol, stratified=stratified)
    check_deterministic(deterministic)
    proj = project(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass)
    indices, probs, total, work = sample(proj, Ks, width, height, samples=samples, eps=eps, seed=seed,
                                         hermite_order=hermite_order, hermite_tol=hermite_tol,
                                         inclusion=inclusion_for(estimator), stratified=stratified)
    image, alpha, depth = composite_sample(proj, features, Ks, indices, probs, background=background,
                                                 composite=composite, estimator=estimator,
                                                 deterministic=deterministic)
    return SplatOutput(image=image, alpha=alpha, depth=depth, total=total, indices=indices, probs=probs,
                       work=work)
