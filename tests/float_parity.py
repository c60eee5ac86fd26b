"""Tolerances of the GPU-vs-CPU parity tests, derived from a float error analysis (tests/test_op_cuda.py).

Both backends run the same core code on the same inputs and sample; they differ in two ways only:

* **FMA contraction.** nvcc contracts ``a*b + c`` into one fused multiply-add by default, the CPU build has
  ``-ffp-contract=off``. A contraction drops one rounding, so every expression keeps the standard bound of its
  operation count k, ``|computed - exact| <= gamma_k * (sum of |terms|)`` with ``gamma_k = k u / (1 - k u)``
  (Higham, *Accuracy and Stability of Numerical Algorithms*, §3.1), on both backends; their difference is at most
  twice that.
* **exp.** The CPU calls glibc's ``exp``/``expf`` (< 1 ulp), CUDA its own (``expf``: 2 ulp, ``exp``: 1 ulp;
  CUDA C++ Programming Guide, "Mathematical Functions", without ``-use_fast_math``). One ulp is at most ``2u``
  relative, so the two values of ``exp`` differ by at most ``6u`` relative (``u = 2^-24`` float32, ``2^-53``
  float64), ``8u`` with the rounding of the product ``amp * exp``.

**A splat's alpha** ``alpha = A exp(-q/2)``, ``q = a dx^2 + 2 b dx dy + c dy^2`` (6 roundings with the two
differences ``dx, dy``): ``|dq| <= gamma_6 q_abs`` per backend with ``q_abs = |a| dx^2 + 2|b||dx dy| + |c| dy^2``
``<= 2 (1 + kappa) q`` for a conic of condition number ``kappa`` (``q_abs <= (a + c + 2|b|) |d|^2 <= 2 tr |d|^2``
and ``q >= lambda_min |d|^2``). So the backends' alphas differ by at most
``alpha (gamma_6 q_abs + 8u) <= A (4 gamma_6 (1 + kappa) / e + 8u) =: A d`` (``q e^{-q/2} <= 2/e``).

**Forward.** Alpha compositing: ``dI/dalpha_j = T_j (f_j - R_j)`` with ``R_j`` a convex combination of the later
features and the background, so ``|dI/dalpha_j| <= 2 T_j F`` (``F`` the largest ``|f|``, ``|bg|`` or depth); the
recurrences add ``gamma_(2m+2) F`` per backend. Additive: ``|dI/dalpha_j| <= F / pi_j``. Summed over a pixel's
slots this bounds ``|I_gpu - I_cpu|``, evaluated on the test's own data (:func:`forward_tolerance`), relative to the
largest ``|I_cpu|`` as the tests measure it. The per-pixel depth adds its own rounding: the ray-plane depth
``t = off / (n . r)`` is accepted only where ``|n . r| >= 10^-2 |r|`` (``kParallelCos``), so its relative error is at
most ``100 gamma_4`` per backend.

**Gradients.** Pass 1 and pass 2 multiply three perturbed factors per term (``3 d`` relative with the
kernel's derivatives, each ``gamma_8`` of rounding) and sum a point's ``n`` entries in the same order on both
backends (``gamma_n`` each, contraction only). So ``|g_gpu - g_cpu| <= (3 d + 2 gamma_8 + 2 gamma_n) sum |terms|``.
The sum of ``|terms|`` is bounded by ``n_max`` times the largest gradient (a point's terms are each at most the
largest single-term gradient; this assumes no point's gradient is a near-total cancellation of terms larger than
the largest gradient of the tensor). :func:`gradient_tolerance`.
"""
from __future__ import annotations

import math

import torch

from nsplat.ops.reference import pixel_centres


def unit_roundoff(dtype: torch.dtype) -> float:
    """``u``: 2^-24 (float32) or 2^-53 (float64)."""
    return 2.0**-24 if dtype == torch.float32 else 2.0**-53


def gamma(k: int, u: float) -> float:
    """``gamma_k = k u / (1 - k u)``: the relative bound of k roundings."""
    return k * u / (1 - k * u)


def alpha_difference(kappa: torch.Tensor, u: float) -> torch.Tensor:
    """``d``: the backends' alphas differ by at most ``A d`` for conics of condition number ``kappa``."""
    return 4 * gamma(6, u) * (1 + kappa) / math.e + 8 * u


def conic_condition(con: torch.Tensor) -> torch.Tensor:
    """Condition numbers of conics ``[..., 3]`` (a, b, c)."""
    a, b, c = con.double().unbind(-1)
    mean, half = (a + c) / 2, torch.sqrt(((a - c) / 2) ** 2 + b**2)
    return (mean + half) / (mean - half).clamp_min(1e-300)


def forward_tolerance(proj, feat: torch.Tensor, bg: torch.Tensor, idx: torch.Tensor, probs: torch.Tensor,
                      composite: str, image: torch.Tensor) -> float:
    """The analysis's bound of ``max|I_gpu - I_cpu| / max|I_cpu|`` for the image, alpha and depth of a sample
    ``idx``/``probs [B,H,W,m]`` of ``proj`` (``[B,N,...]``), ``feat [N,C]``, ``bg [C]``; ``image``: the CPU's."""
    u = unit_roundoff(feat.dtype)
    B, H, W, m = idx.shape
    pix = pixel_centres(W, H, torch.float64, idx.device).reshape(H, W, 2)
    F = max(float(feat.abs().max()) if feat.numel() else 0.0, float(bg.abs().max()), 1e-300)
    F = max(F, float(proj.depths.abs().max()) if proj.depths.numel() else 0.0)
    worst = 0.0
    for b in range(B):
        k = idx[b].long().clamp_min(0)
        filled = idx[b] >= 0
        d = pix[:, :, None, :] - proj.means2d[b].double()[k]
        con = proj.conics[b].double()[k]
        q = con[..., 0] * d[..., 0] ** 2 + 2 * con[..., 1] * d[..., 0] * d[..., 1] + con[..., 2] * d[..., 1] ** 2
        A = proj.amps[b].double()[k]
        alpha = torch.where(filled, (A * torch.exp(-q / 2)).clamp_max(0.99), torch.zeros_like(q))
        dj = torch.where(filled, A * alpha_difference(conic_condition(con), u), torch.zeros_like(q))
        if composite == "alpha":
            T = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1 - alpha[..., :-1]], -1), -1)
            sens = 2 * T
        else:
            sens = torch.where(filled, 1 / probs[b].double().clamp_min(1e-8), torch.zeros_like(q))
        bound = (sens * dj).sum(-1) * F + 2 * gamma(2 * m + 2, u) * F + 2 * 100 * gamma(4, u) * F
        worst = max(worst, float(bound.max()))
    return worst / max(float(image.abs().max()), 1e-300)


def gradient_tolerance(fwd_tol_terms: float, idx: torch.Tensor, dtype: torch.dtype) -> float:
    """The analysis's bound of ``max|g_gpu - g_cpu| / max|g_cpu|``: ``n_max (3 d + 2 gamma_8 + 2 gamma_n_max)`` with
    ``d`` the largest per-slot alpha difference ``fwd_tol_terms`` and ``n_max`` the most entries of one point."""
    u = unit_roundoff(dtype)
    filled = idx[idx >= 0].long()
    n_max = int(torch.bincount(filled).max()) if filled.numel() else 1
    return n_max * (3 * fwd_tol_terms + 2 * gamma(8, u) + 2 * gamma(n_max, u))


def largest_alpha_difference(proj, dtype: torch.dtype) -> float:
    """``d`` at the worst-conditioned visible conic of ``proj``."""
    valid = proj.amps > 0
    if not bool(valid.any()):
        return 8 * unit_roundoff(dtype)
    return float(alpha_difference(conic_condition(proj.conics[valid]), unit_roundoff(dtype)).max())
