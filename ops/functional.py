"""The sampled splatting op: ``splat`` (project → sample → composite) and its stages.

Stages (each usable on its own, PyTorch3D style):
    :func:`nsplat.ops.project`  differentiable EWA projection (PyTorch autograd)
    :func:`sample`              per-pixel sequential Poisson sample over the radix tree (native, no grad)
    :func:`composite_sample`    compositing of a given sample with the estimator's backward (native)

Each validates its arguments (``ops/validation.py``) and then calls the custom ops of
``ops/library.py`` (``nsplat::sample``, ``nsplat::composite_forward``), which dispatch on the device and
carry the autograd, fake kernels and ``torch.compile`` support. Inside an autocast region the stages run
in float32 (docs/op.md §7).
"""
from __future__ import annotations

import dataclasses

import torch

from .build import backend
from .library import _entries_by_point, _entries_by_point_sorted, composite_forward_op, sample_op  # noqa: F401 - re-exported (tests, benchmarks)
from .output import SplatOutput
from .projection import Projected, project_checked
from .validation import (
    COMPOSITES,
    ESTIMATORS,
    INCLUSIONS,
    check_allocation,
    check_backface_cull,
    check_composite_call,
    check_deterministic,
    check_devices,
    check_geometry,
    check_sample_call,
    check_sampling,
    check_settings,
    inclusion_for,
    native_estimator,
)
from .value_checks import value_checks

_PROJECTED_FIELDS = ("means2d", "conics", "amps", "normals_cam", "plane_offsets", "depths", "sigma2")
_LOW_PRECISION = (torch.float16, torch.bfloat16)


def _autocast_on(t: object) -> bool:
    """Whether an autocast region is active for the device type of tensor ``t`` (the op then runs in
    float32: docs/op.md "Using the op in other networks"); False for a non-tensor (validation reports it)."""
    return isinstance(t, torch.Tensor) and torch.is_autocast_enabled(t.device.type)


def _to_float32(t: object) -> object:
    """``t`` in float32 when it is a float16/bfloat16 tensor (as autocast produces), else ``t`` itself."""
    return t.float() if isinstance(t, torch.Tensor) and t.dtype in _LOW_PRECISION else t


def _projected_float32(proj: Projected) -> Projected:
    """``proj`` with its float16/bfloat16 fields in float32 (a projection run under autocast)."""
    if not isinstance(proj, Projected):
        return proj
    return Projected(**{f.name: _to_float32(getattr(proj, f.name)) for f in dataclasses.fields(proj)})


def sampler_isa() -> str:
    """The instruction set of the CPU sampler's tile search in this process: the widest this CPU runs ("avx512",
    "avx2" or "base"), or the one the environment variable ``NSPLAT_CPU_SIMD`` names (read at every call; all of
    them give the same bits, docs/op.md §4). Raises ``ValueError`` for a name the build lacks or the CPU cannot run."""
    return backend(torch.device("cpu")).sampler_isa("auto")


def _seed_tensor(seed: int | torch.Tensor) -> torch.Tensor:
    """The seed as the int64 tensor the custom op takes, 0-dim or ``[B]`` (:func:`nsplat.ops.library.sample_op`)."""
    if isinstance(seed, torch.Tensor):
        return seed.detach().to(torch.int64)
    return torch.tensor(seed, dtype=torch.int64)


@torch.no_grad()
def sample(proj: Projected, Ks: torch.Tensor, width: int, height: int, *, samples: int = 40, eps: float = 0.01,
           seed: int = 0, hermite_order: int = 8, hermite_tol: float = 1e-3, inclusion: str = "threshold",
           stratified: bool = False) -> tuple[torch.Tensor, ...]:
    """Draw each pixel's SPS sample of ``samples`` points (docs/method.md "Sampling").

    Args:
        proj: projected surfels of ``B`` cameras (:func:`nsplat.ops.project`).
        Ks: ``[B,3,3]`` intrinsics (pixel rays for per-pixel depth ordering).
        samples: sample size ``m`` per pixel. eps: bound on the probability that a pixel's sample
            differs from the exact SPS sample. seed: RNG seed, an int or a 0-dim integer tensor (``u`` is a hash of
            seed,
            camera, pixel, point). hermite_order: maximum Hermite order per dimension (0 disables expansions).
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
    check_devices(Ks=Ks)
    if _autocast_on(Ks):
        with torch.autocast(Ks.device.type, enabled=False):
            return sample(_projected_float32(proj), _to_float32(Ks), width, height, samples=samples, eps=eps,
                          seed=seed, hermite_order=hermite_order, hermite_tol=hermite_tol, inclusion=inclusion,
                          stratified=stratified)
    if inclusion not in INCLUSIONS:
        raise ValueError(f"inclusion: expected one of {INCLUSIONS}, got {inclusion!r}")
    with value_checks():
        check_sample_call(proj, Ks, width, height, samples=samples, eps=eps, seed=seed, hermite_order=hermite_order,
                          hermite_tol=hermite_tol, stratified=stratified)
    return _sample_op(proj, Ks, width, height, samples, eps, seed, hermite_order, hermite_tol, inclusion, stratified)


def _sample_op(proj: Projected, Ks: torch.Tensor, width: int, height: int, samples: int, eps: float, seed: int,
               hermite_order: int, hermite_tol: float, inclusion: str, stratified: bool) -> tuple[torch.Tensor, ...]:
    """The native sampler on validated arguments (:func:`sample` without its checks)."""
    fields = (proj.means2d, proj.conics, proj.amps, proj.sigma2, proj.normals_cam, proj.plane_offsets, proj.depths)
    return sample_op(*(t.detach() for t in fields), Ks.detach(), _seed_tensor(seed), width, height, samples,
                     float(eps), hermite_order, float(hermite_tol), INCLUSIONS.index(inclusion), bool(stratified))


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
        proj: projected surfels ``[B,N,...]``. features: ``[N,C]``, or ``[B,N,C]`` (camera ``b`` sees
            ``features[b]``; their gradient is per camera too). Ks: ``[B,3,3]``.
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
    check_devices(Ks=Ks, features=features)
    if _autocast_on(Ks):
        with torch.autocast(Ks.device.type, enabled=False):
            return composite_sample(_projected_float32(proj), _to_float32(features), _to_float32(Ks), indices,
                                    _to_float32(probs), background=_to_float32(background), composite=composite,
                                    estimator=estimator, deterministic=deterministic)
    with value_checks():
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
    return _composite_op(proj, features, Ks, indices, probs, background, composite, estimator, deterministic)


def _composite_op(proj: Projected, features: torch.Tensor, Ks: torch.Tensor, indices: torch.Tensor,
                  probs: torch.Tensor, background: torch.Tensor | None, composite: str, estimator: str,
                  deterministic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The native compositor on validated arguments (:func:`composite_sample` without its checks)."""
    bg = background if background is not None else features.new_zeros(features.shape[-1])
    image, alpha, depth = composite_forward_op(proj.means2d, proj.conics, proj.amps, proj.normals_cam,
                                               proj.plane_offsets, proj.depths, Ks.detach(), features, bg,
                                               indices, probs.detach(), COMPOSITES.index(composite),
                                               native_estimator(estimator), deterministic)
    return image, alpha, depth


def splat(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
          features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
          samples: int = 40, eps: float = 0.01, estimator: str = "ht", composite: str = "alpha",
          background: torch.Tensor | None = None, near: float = 0.01, far: float = 1e10, lowpass: float = 1.0,
          seed: int = 0, hermite_order: int = 8, hermite_tol: float = 1e-3, deterministic: bool = True,
          stratified: bool = False, backface_cull: bool = False) -> SplatOutput:
    """Render surfel features by EWA surface splatting with per-pixel Poisson sampling (backward: see ``estimator``).

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
        opacities: ``[N]`` in [0, 1]. features: ``[N,C]`` any C >= 1 (RGB or learned, signed), or ``[B,N,C]``:
            camera ``b`` sees ``features[b]`` (view-dependent colour of several views in one call).
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
            depth. lowpass: screen-space low-pass variance in px² (the paper's +I is 1). seed: RNG seed: an int, a 0-dim
            integer tensor (a seed that changes every step without recompiling under ``torch.compile``), or a ``[B]``
            integer tensor, one seed per camera: camera ``b`` then samples exactly as the only camera of a call
            with seed ``seed[b]``, so views rendered in one call sample as the same views rendered one by one.
        hermite_order, hermite_tol: tree expansion order cap and relative truncation tolerance.
        deterministic: True (default) gives run-to-run and thread-count independent, bitwise identical
            gradients (fixed-order per-point gather). False selects the faster single-pass CPU backward
            that scatters with atomics (equal up to float rounding). CUDA has only the deterministic
            backward; ``False`` on CUDA tensors silently uses it.
        stratified: stratified uniforms across pixels (see :func:`sample`); off by default.
        backface_cull: cull, per camera, the surfels whose normal faces away from it (classic surface
            splatting); off by default (two-sided surfels). On a closed surface about half of a pixel's
            samples are back faces (fitted lego: 47–51 %); culled, they leave the m slots to the visible
            side and the sampler's tree to the facing points.

    Returns:
        :class:`SplatOutput`: ``image [B,H,W,C]``, ``alpha [B,H,W,1]``, ``depth [B,H,W,1]``,
        ``total [B,H,W,1]`` (Λ̂), ``indices [B,H,W,m]`` int32, ``probs [B,H,W,m]``, ``work [B,H,W,1]``.
    """
    check_devices(means=means, normals=normals, scales=scales, opacities=opacities, features=features,
                  viewmats=viewmats, Ks=Ks, background=background)
    if _autocast_on(means):
        with torch.autocast(means.device.type, enabled=False):
            f32 = [_to_float32(t) for t in (means, normals, scales, opacities, features, viewmats, Ks)]
            return splat(*f32, width, height, samples=samples, eps=eps, estimator=estimator, composite=composite,
                         background=_to_float32(background), near=near, far=far, lowpass=lowpass, seed=seed,
                         hermite_order=hermite_order, hermite_tol=hermite_tol, deterministic=deterministic,
                         stratified=stratified, backface_cull=backface_cull)
    with value_checks():  # one host read for every value check of the inputs
        N, C, B = check_geometry(means, normals, scales, opacities, features, viewmats, Ks)
        check_settings(width=width, height=height, near=near, far=far, lowpass=lowpass, composite=composite,
                       background=background, C=C, dtype=means.dtype, device=means.device)
        check_sampling(samples=samples, eps=eps, estimator=estimator, seed=seed, hermite_order=hermite_order,
                       hermite_tol=hermite_tol, stratified=stratified, cameras=B)
        check_deterministic(deterministic)
        check_backface_cull(backface_cull)
    for stage in ("sample", "composite"):  # before any work: the projection alone can take minutes
        check_allocation(B=B, N=N, C=C, width=width, height=height, samples=samples, dtype=means.dtype,
                         device=means.device, what=stage)
    # the inputs are checked above; the stages' own checks would re-validate values this op produced
    proj = project_checked(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass,
                           backface_cull=backface_cull)
    with torch.no_grad():
        indices, probs, total, work = _sample_op(proj, Ks, width, height, samples, eps, seed, hermite_order,
                                                 hermite_tol, inclusion_for(estimator), stratified)
    image, alpha, depth = _composite_op(proj, features, Ks, indices, probs, background, composite, estimator,
                                        deterministic)
    return SplatOutput(image=image, alpha=alpha, depth=depth, total=total, indices=indices, probs=probs,
                       work=work, means2d=proj.means2d)
