"""Argument checks for the op, run before any native code.

Every failure raises ``TypeError`` (wrong Python/tensor type or dtype) or ``ValueError`` (wrong
shape, device, range or non-finite values) whose message starts with the argument's name and states
what was expected.
"""
from __future__ import annotations

import numbers

import torch

#: Gradient estimators (docs/op.md "Estimators"): "ht" Horvitz–Thompson with the priority-sampling
#: threshold probabilities (exactly unbiased in additive mode), "ht-pips" Horvitz–Thompson with the πps
#: target probabilities (slightly biased), "paper" eq. 3 as printed, "sampled" no reweighting.
ESTIMATORS = ("ht", "ht-pips", "paper", "sampled")
#: Inclusion probabilities the sampler returns: exact conditional (priority threshold) or πps targets.
INCLUSIONS = ("threshold", "pips")
COMPOSITES = ("alpha", "additive")
FLOAT_DTYPES = (torch.float32, torch.float64)


def _tensor(name: str, t: object) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if t.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name}: expected dtype float32 or float64, got {t.dtype}")
    return t


def _shape(name: str, t: torch.Tensor, expected: tuple[object, ...], text: str) -> None:
    ok = t.dim() == len(expected) and all(e is None or s == e for s, e in zip(t.shape, expected))
    if not ok:
        raise ValueError(f"{name}: expected shape {text}, got {list(t.shape)}")


def _finite(name: str, t: torch.Tensor) -> None:
    if t.numel() and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or Inf")


def _int(name: str, v: object, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise TypeError(f"{name}: expected an int, got {type(v).__name__}")
    if int(v) < lo:
        raise ValueError(f"{name}: expected an int >= {lo}, got {v}")
    return int(v)


def _real(name: str, v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise TypeError(f"{name}: expected a real number, got {type(v).__name__}")
    f = float(v)
    if f != f or f in (float("inf"), float("-inf")):
        raise ValueError(f"{name}: expected a finite number, got {v}")
    return f


def check_geometry(means, normals, scales, opacities, features, viewmats, Ks) -> tuple[int, int, int]:
    """Check the scene and camera tensors; returns ``(N, C, B)``.

    Shapes: ``means [N,3]``, ``normals [N,3]`` (non-zero), ``scales [N,2]`` (> 0),
    ``opacities [N]`` (in [0, 1]), ``features [N,C]``, ``viewmats [B,4,4]`` (last row 0 0 0 1),
    ``Ks [B,3,3]`` (``fx, fy > 0``, last row 0 0 1, ``K[1,0] = 0``); one float dtype and one device.
    """
    names = ("means", "normals", "scales", "opacities", "features", "viewmats", "Ks")
    tensors = [_tensor(n, t) for n, t in zip(names, (means, normals, scales, opacities, features, viewmats, Ks))]
    dtype, device = tensors[0].dtype, tensors[0].device
    for n, t in zip(names, tensors):
        if t.dtype != dtype:
            raise TypeError(f"{n}: expected dtype {dtype} (the dtype of means), got {t.dtype}")
        if t.device != device:
            raise ValueError(f"{n}: expected device {device} (the device of means), got {t.device}")
    _shape("means", means, (None, 3), "[N, 3]")
    N = means.shape[0]
    _shape("normals", normals, (N, 3), f"[N, 3] with N={N}")
    _shape("scales", scales, (N, 2), f"[N, 2] with N={N}")
    _shape("opacities", opacities, (N,), f"[N] with N={N}")
    if features.dim() != 2 or features.shape[0] != N or features.shape[1] < 1:
        raise ValueError(f"features: expected shape [N, C] with N={N} and C >= 1, got {list(features.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4) or viewmats.shape[0] < 1:
        raise ValueError(f"viewmats: expected shape [B, 4, 4] with B >= 1, got {list(viewmats.shape)}")
    B = viewmats.shape[0]
    _shape("Ks", Ks, (B, 3, 3), f"[B, 3, 3] with B={B}")
    for n, t in zip(names, tensors):
        _finite(n, t)
    if N:
        if bool((normals.norm(dim=-1) == 0).any()):
            raise ValueError("normals: every normal must have non-zero length")
        if bool((scales <= 0).any()):
            raise ValueError("scales: expected values > 0 (world-unit tangent standard deviations)")
        if bool(((opacities < 0) | (opacities > 1)).any()):
            raise ValueError("opacities: expected values in [0, 1]")
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype, device=device)
    if not bool((viewmats[:, 3, :] == last).all()):
        raise ValueError("viewmats: expected world-to-camera matrices with last row [0, 0, 0, 1]")
    if not bool((Ks[:, 2, :] == last[1:]).all()):
        raise ValueError("Ks: expected intrinsics with last row [0, 0, 1]")
    if bool((Ks[:, 1, 0] != 0).any()):
        raise ValueError("Ks: expected K[1, 0] == 0 (upper-triangular intrinsics)")
    if bool(((Ks[:, 0, 0] <= 0) | (Ks[:, 1, 1] <= 0)).any()):
        raise ValueError("Ks: expected focal lengths fx = K[0,0] > 0 and fy = K[1,1] > 0")
    return N, features.shape[1], B


def check_settings(*, width, height, near, far, lowpass, composite, background, C, dtype, device) -> None:
    """Check image size, clipping range, low-pass variance, compositing mode and background."""
    _int("width", width, 1)
    _int("height", height, 1)
    n, f = _real("near", near), _real("far", far)
    if n <= 0:
        raise ValueError(f"near: expected a value > 0, got {near}")
    if not f > n:
        raise ValueError(f"far: expected a value > near ({near}), got {far}")
    if _real("lowpass", lowpass) < 0:
        raise ValueError(f"lowpass: expected a variance >= 0 (pixels^2), got {lowpass}")
    if composite not in COMPOSITES:
        raise ValueError(f"composite: expected one of {COMPOSITES}, got {composite!r}")
    if background is not None:
        _tensor("background", background)
        if background.dtype != dtype:
            raise TypeError(f"background: expected dtype {dtype}, got {background.dtype}")
        if background.device != device:
            raise ValueError(f"background: expected device {device}, got {background.device}")
        _shape("background", background, (C,), f"[C] with C={C}")
        _finite("background", background)


def inclusion_for(estimator: str) -> str:
    """The inclusion probabilities an estimator weights by: "threshold" for "ht", "pips" otherwise."""
    return "threshold" if estimator == "ht" else "pips"


def native_estimator(estimator: str) -> int:
    """The native estimator id (csrc/core/common.h ``Estimator``): both HT variants weight by 1/π."""
    return {"ht": 0, "ht-pips": 0, "paper": 1, "sampled": 2}[estimator]


def check_sampling(*, samples, eps, estimator, seed, hermite_order, hermite_tol, stratified=False) -> None:
    """Check the sampler and estimator settings."""
    if not isinstance(stratified, bool):
        raise TypeError(f"stratified: expected a bool, got {type(stratified).__name__}")
    _int("samples", samples, 1)
    e = _real("eps", eps)
    if not 0 < e <= 1:
        raise ValueError(f"eps: expected a probability in (0, 1], got {eps}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
    _int("seed", seed, 0)
    if int(seed) >= 2**63:
        raise ValueError(f"seed: expected a value < 2**63, got {seed}")
    order = _int("hermite_order", hermite_order, 0)
    if order > 16:
        raise ValueError(f"hermite_order: expected an int in [0, 16], got {hermite_order}")
    t = _real("hermite_tol", hermite_tol)
    if not 0 < t < 1:
        raise ValueError(f"hermite_tol: expected a value in (0, 1), got {hermite_tol}")


def check_deterministic(deterministic) -> None:
    """``deterministic`` must be a bool (fixed-order backward vs atomic-scatter backward)."""
    if not isinstance(deterministic, bool):
        raise TypeError(f"deterministic: expected a bool, got {type(deterministic).__name__}")
