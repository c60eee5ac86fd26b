"""Argument checks for the op, run before any native code.

Every failure raises ``TypeError`` (wrong Python/tensor type or dtype) or ``ValueError`` (wrong
shape, device, range or non-finite values) whose message starts with the argument's name and states
what was expected.

Under ``torch.compile`` (:func:`values_checked` is False) the checks of types, dtypes, shapes, devices
and Python settings run as always (they are static while tracing), but the data-dependent checks of
tensor *values* (NaN/Inf, signs and ranges, rigid viewmats, projection overflow, index and probability
ranges) are skipped: they would force a graph break on every call. Run a compiled model's inputs through
the op once eagerly to check them (docs/op.md "Using the op in other networks").

The data-dependent checks go through ``ops/value_checks.py`` (run together, in one read back to the host).
"""
from __future__ import annotations

import numbers
import os

import torch

from .value_checks import fail_if, value_checks

#: Gradient estimators (docs/op.md "Estimators"): "ht" Horvitz–Thompson with the priority-sampling
#: threshold probabilities (exactly unbiased in additive mode), "ht-pips" Horvitz–Thompson with the πps
#: target probabilities (slightly biased), "paper" eq. 3 as printed, "sampled" no reweighting.
ESTIMATORS = ("ht", "ht-pips", "paper", "sampled")
#: Inclusion probabilities the sampler returns: exact conditional (priority threshold) or πps targets.
INCLUSIONS = ("threshold", "pips")
COMPOSITES = ("alpha", "additive")
FLOAT_DTYPES = (torch.float32, torch.float64)
#: Largest ``samples``: the native sampler counts slots of a pixel in 32-bit ints.
MAX_SAMPLES = 2**31 - 1
#: Allowed deviation of ``R·Rᵀ`` from ``s²·I`` (relative to ``s²``) for a viewmat's 3×3 part ``R``.
RIGID_TOL = {torch.float32: 1e-4, torch.float64: 1e-5}
#: float32, no low-pass: a visible splat whose ``det Σ`` (px⁴) is in ``(0, this)`` gets NaN/Inf gradients
#: (measured: NaN from ``det Σ ≈ 1e-28``, i.e. σ ≈ 1e-7 px; fine at 1e-24); four decades of margin.
TINY_DET_F32 = 1e-20
#: Device types the op runs on (the native CPU and CUDA backends; the dense oracle too).
DEVICE_TYPES = ("cpu", "cuda")


def values_checked() -> bool:
    """Whether the data-dependent value checks run: always in eager mode, never while ``torch.compile``
    traces (module docstring)."""
    return not torch.compiler.is_compiling()


class AllocationError(ValueError):
    """The outputs or workspace of a call cannot fit in this machine's memory (raised before allocating)."""


def check_devices(**tensors: object) -> None:
    """Refuse tensors on a device type the op does not run on (``meta``, ``xla``, ...) by name, before any
    autocast query or value check touches them (those fail with messages that name no argument)."""
    for name, t in tensors.items():
        if isinstance(t, torch.Tensor) and t.device.type not in DEVICE_TYPES:
            raise ValueError(f"{name}: expected a tensor on the CPU or a CUDA device, got device {t.device}")


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
    if values_checked() and t.numel():
        fail_if(~torch.isfinite(t).all(), lambda: f"{name}: contains NaN or Inf")


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
    """Check the scene and camera tensors; returns ``(N, C, B)`` (``C = 0`` when ``features`` is None).

    Shapes: ``means [N,3]``, ``normals [N,3]`` (non-zero), ``scales [N,2]`` (> 0),
    ``opacities [N]`` (in [0, 1]), ``features [N,C]`` or ``[B,N,C]`` (per camera), ``viewmats [B,4,4]`` (last
    row 0 0 0 1, 3×3 part a rotation times a uniform scale), ``Ks [B,3,3]`` (``fx, fy > 0``, last row 0 0 1,
    ``K[1,0] = 0``); one float dtype and one device.
    """
    names = ("means", "normals", "scales", "opacities", "features", "viewmats", "Ks")
    given = (means, normals, scales, opacities, features, viewmats, Ks)
    check_devices(**dict(zip(names, given)))
    if features is None:
        names, given = names[:4] + names[5:], given[:4] + given[5:]
    tensors = [_tensor(n, t) for n, t in zip(names, given)]
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
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4) or viewmats.shape[0] < 1:
        raise ValueError(f"viewmats: expected shape [B, 4, 4] with B >= 1, got {list(viewmats.shape)}")
    B = viewmats.shape[0]
    if features is not None:
        check_feature_shape(features, B, N, "the cameras of viewmats")
    _shape("Ks", Ks, (B, 3, 3), f"[B, 3, 3] with B={B}")
    for n, t in zip(names, tensors):
        _finite(n, t)
    if values_checked():
        _check_geometry_values(N, normals, scales, opacities, viewmats, Ks)
    return N, (features.shape[-1] if features is not None else 0), B


def check_feature_shape(features: torch.Tensor, B: int, N: int, cameras: str) -> None:
    """``features`` is ``[N,C]`` (every camera sees them) or ``[B,N,C]`` (camera ``b`` sees ``features[b]``)."""
    shared = features.dim() == 2 and features.shape[0] == N
    per_camera = features.dim() == 3 and features.shape[:2] == (B, N)
    if not (shared or per_camera) or features.shape[-1] < 1:
        raise ValueError(f"features: expected shape [N, C] or [B, N, C] with N={N}, B={B} ({cameras}) and C >= 1, "
                         f"got {list(features.shape)}")


def _check_geometry_values(N: int, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                           viewmats: torch.Tensor, Ks: torch.Tensor) -> None:
    """The data-dependent checks of :func:`check_geometry` (eager only, see :func:`values_checked`)."""
    if N:
        fail_if((normals.norm(dim=-1) == 0).any(), lambda: "normals: every normal must have non-zero length")
        fail_if((scales <= 0).any(), lambda: "scales: expected values > 0 (world-unit tangent standard deviations)")
        fail_if(((opacities < 0) | (opacities > 1)).any(), lambda: "opacities: expected values in [0, 1]")
    # compared with Python scalars: a constant tensor built on the device would be a copy from the host
    fail_if((viewmats[:, 3, :3] != 0).any() | (viewmats[:, 3, 3] != 1).any(),
            lambda: "viewmats: expected world-to-camera matrices with last row [0, 0, 0, 1]")
    fail_if((Ks[:, 2, :2] != 0).any() | (Ks[:, 2, 2] != 1).any(),
            lambda: "Ks: expected intrinsics with last row [0, 0, 1]")
    fail_if((Ks[:, 1, 0] != 0).any(), lambda: "Ks: expected K[1, 0] == 0 (upper-triangular intrinsics)")
    fail_if(((Ks[:, 0, 0] <= 0) | (Ks[:, 1, 1] <= 0)).any(),
            lambda: "Ks: expected focal lengths fx = K[0,0] > 0 and fy = K[1,1] > 0")
    check_rigid(viewmats)


def check_rigid(viewmats: torch.Tensor) -> None:
    """The 3×3 part ``R`` of every viewmat must be a rotation (or reflection) times a uniform scale ``s > 0``:
    ``R·Rᵀ = s²·I`` up to :data:`RIGID_TOL`. Shear or non-uniform scale would transform the normals
    wrongly (they are rotated by ``R``), so they are rejected, naming the first bad camera."""
    R = viewmats[:, :3, :3].detach()
    G = R @ R.transpose(1, 2)
    s2 = G.diagonal(dim1=1, dim2=2).mean(-1)
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    dev = (G - s2[:, None, None] * eye).abs().amax(dim=(1, 2)) / torch.where(s2 > 0, s2, torch.ones_like(s2))
    tol = RIGID_TOL[R.dtype]
    bad = (s2 <= 0) | ~(dev <= tol)
    def message() -> str:
        b = int(torch.nonzero(bad)[0, 0])
        return (f"viewmats: camera {b}: the 3x3 part is not a rotation times a uniform scale "
                f"(|R Rᵀ - s² I| / s² = {float(dev[b]):.3g} > {tol:g}); shear and non-uniform scale "
                f"are not supported (normals would be transformed wrongly)")

    fail_if(bad.any(), message)


def check_range(*, near, far, lowpass) -> None:
    """Check the clipping range ``0 < near < far`` and the low-pass variance ``>= 0``."""
    n, f = _real("near", near), _real("far", far)
    if n <= 0:
        raise ValueError(f"near: expected a value > 0, got {near}")
    if not f > n:
        raise ValueError(f"far: expected a value > near ({near}), got {far}")
    if _real("lowpass", lowpass) < 0:
        raise ValueError(f"lowpass: expected a variance >= 0 (pixels^2), got {lowpass}")


def check_settings(*, width, height, near, far, lowpass, composite, background, C, dtype, device) -> None:
    """Check image size, clipping range, low-pass variance, compositing mode and background."""
    _int("width", width, 1)
    _int("height", height, 1)
    check_range(near=near, far=far, lowpass=lowpass)
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


def check_sampling(*, samples, eps, estimator, seed, hermite_order, hermite_tol, stratified=False,
                   cameras=None) -> None:
    """Check the sampler and estimator settings (``cameras``: the call's ``B``, which a ``[B]`` seed must match)."""
    if not isinstance(stratified, bool):
        raise TypeError(f"stratified: expected a bool, got {type(stratified).__name__}")
    if _int("samples", samples, 1) > MAX_SAMPLES:
        raise ValueError(f"samples: expected an int in [1, {MAX_SAMPLES}], got {samples}")
    e = _real("eps", eps)
    if not 0 < e <= 1:
        raise ValueError(f"eps: expected a probability in (0, 1], got {eps}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
    if isinstance(seed, torch.Tensor):  # a per-step seed as a graph input (Splatter); range checked eagerly
        if seed.dim() > 1 or seed.dtype.is_floating_point or seed.dtype.is_complex or seed.dtype == torch.bool:
            raise TypeError(f"seed: expected an int, a 0-dim integer tensor or one seed per camera [B], got "
                            f"{seed.dtype} {list(seed.shape)}")
        if seed.dim() == 1 and cameras is not None and seed.shape[0] != cameras:
            raise ValueError(f"seed: one seed per camera expected, got {seed.shape[0]} seeds for {cameras} cameras")
        if values_checked() and seed.numel():
            fail_if((seed < 0).any(), lambda: f"seed: expected values in [0, 2**63), got {seed.min().item()}")
    else:
        _int("seed", seed, 0)
        if int(seed) >= 2**63:
            raise ValueError(f"seed: expected a value < 2**63, got {seed}")
    order = _int("hermite_order", hermite_order, 0)
    if order > 16:
        raise ValueError(f"hermite_order: expected an int in [0, 16], got {hermite_order}")
    t = _real("hermite_tol", hermite_tol)
    if not 0 < t < 1:
        raise ValueError(f"hermite_tol: expected a value in (0, 1), got {hermite_tol}")


def check_backface_cull(backface_cull) -> None:
    """``backface_cull`` must be a bool (cull surfels facing away from each camera, or render both sides)."""
    if not isinstance(backface_cull, bool):
        raise TypeError(f"backface_cull: expected a bool, got {type(backface_cull).__name__}")


def check_deterministic(deterministic) -> None:
    """``deterministic`` must be a bool (fixed-order backward vs atomic-scatter backward)."""
    if not isinstance(deterministic, bool):
        raise TypeError(f"deterministic: expected a bool, got {type(deterministic).__name__}")


def _physical_memory() -> int:
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 2**40


#: Physical RAM in bytes, read once at import (a constant while torch.compile traces; no os call in the graph).
PHYSICAL_MEMORY = _physical_memory()


def memory_limit(device: torch.device) -> int:
    """Bytes a single call may at most allocate: the device's total memory (physical RAM on CPU)."""
    if device.type == "cuda":
        return int(torch.cuda.get_device_properties(device).total_memory)
    return PHYSICAL_MEMORY


def check_allocation(*, B: int, N: int, C: int, width: int, height: int, samples: int, dtype: torch.dtype,
                     device: torch.device, what: str = "sample") -> int:
    """Raise :class:`AllocationError` before allocating when a call's outputs and workspace exceed the
    device's memory; returns the bytes needed. Python ints throughout (no 32-bit wrap).

    ``what``: ``"sample"`` (indices, π, Λ̂, work per pixel and the tree per point) or ``"composite"``
    (image, alpha, depth and the backward's per-slot derivatives).
    """
    S = torch.empty((), dtype=dtype).element_size()
    pixels = int(B) * int(height) * int(width)
    slots = pixels * int(samples)
    if what == "sample":
        need = slots * (4 + S) + pixels * (S + 4) + int(B) * int(N) * 256
    else:
        need = pixels * (int(C) + 2) * S + slots * (2 * S + 16)
    limit = memory_limit(device)
    if need > limit:
        raise AllocationError(
            f"width/height/samples: {B} camera(s) x {width}x{height} px x samples={samples} need about "
            f"{need / 2**30:.3g} GiB ({need} bytes) for the {what} stage, more than the {limit / 2**30:.3g} GiB "
            f"of memory of {device}; reduce width, height, samples or the number of cameras")
    return need


def check_dense_allocation(*, B: int, N: int, C: int, width: int, height: int, grad: bool, dtype: torch.dtype,
                           device: torch.device) -> int:
    """:func:`check_allocation` for the dense oracle (:func:`nsplat.ops.splat_dense`): its outputs (image,
    alpha, depth, Λ) and, when autograd records (``grad``), the ``C + 24`` values per pixel and point that
    its graph keeps (measured with every input learnable: 23.8 at C = 1, 39.4 at C = 16, float32; without
    autograd the pixels are evaluated in bounded chunks)."""
    S = torch.empty((), dtype=dtype).element_size()
    pixels = int(B) * int(height) * int(width)
    need = pixels * (int(C) + 3) * S + (pixels * int(N) * (int(C) + 24) * S if grad else 0)
    limit = memory_limit(device)
    if need > limit:
        graph = f" x {N} points (autograd keeps every pixel-point term)" if grad else ""
        raise AllocationError(
            f"width/height: {B} camera(s) x {width}x{height} px{graph} need about {need / 2**30:.3g} GiB "
            f"({need} bytes) in the dense oracle, more than the {limit / 2**30:.3g} GiB of memory of {device}; "
            f"reduce width, height or the number of cameras{', or run it under torch.no_grad()' if grad else ''}")
    return need


def check_projected(proj, Ks: torch.Tensor) -> tuple[int, int]:
    """Check a :class:`~nsplat.ops.projection.Projected` (from :func:`project` or hand-made) and ``Ks``;
    returns ``(B, N)``. Every field is ``[B, N, ...]``, finite, of one float dtype and device."""
    fields = {"means2d": 2, "conics": 3, "amps": None, "normals_cam": 3, "plane_offsets": None, "depths": None,
              "sigma2": None}
    for name in (*fields, "valid"):
        if not isinstance(getattr(proj, name, None), torch.Tensor):
            raise TypeError(f"proj.{name}: expected a torch.Tensor (proj must come from nsplat.ops.project)")
    amps = _tensor("proj.amps", proj.amps)
    if amps.dim() != 2:
        raise ValueError(f"proj.amps: expected shape [B, N], got {list(amps.shape)}")
    B, N = amps.shape
    if B < 1:
        raise ValueError("proj: expected at least one camera (B >= 1)")
    for name, last in fields.items():
        t = _tensor(f"proj.{name}", getattr(proj, name))
        if t.dtype != amps.dtype or t.device != amps.device:
            raise TypeError(f"proj.{name}: expected {amps.dtype} on {amps.device} (as proj.amps), got {t.dtype} "
                            f"on {t.device}")
        want = (B, N) if last is None else (B, N, last)
        _shape(f"proj.{name}", t, want, f"{list(want)}")
        _finite(f"proj.{name}", t)
    if tuple(proj.valid.shape) != (B, N):
        raise ValueError(f"proj.valid: expected shape {[B, N]}, got {list(proj.valid.shape)}")
    if values_checked():
        fail_if((proj.amps < 0).any() | (proj.sigma2 < 0).any(), lambda: "proj.amps, proj.sigma2: expected values >= 0")
    _tensor("Ks", Ks)
    if Ks.device != amps.device:
        raise ValueError(f"Ks: expected device {amps.device} (the device of proj), got {Ks.device}")
    _shape("Ks", Ks, (B, 3, 3), f"[B, 3, 3] with B={B} (the cameras of proj)")
    _finite("Ks", Ks)
    return B, N


def check_sample_call(proj, Ks, width, height, *, samples, eps, seed, hermite_order, hermite_tol,
                      stratified=False) -> None:
    """All checks of the public :func:`nsplat.ops.sample` stage, memory included."""
    B, N = check_projected(proj, Ks)
    _int("width", width, 1)
    _int("height", height, 1)
    check_sampling(samples=samples, eps=eps, estimator="ht", seed=seed, hermite_order=hermite_order,
                   hermite_tol=hermite_tol, stratified=stratified, cameras=B)
    check_allocation(B=B, N=N, C=0, width=width, height=height, samples=samples, dtype=proj.amps.dtype,
                     device=proj.amps.device, what="sample")


def check_composite_call(proj, features, Ks, indices, probs, background, composite, estimator,
                         deterministic) -> None:
    """All checks of the public :func:`nsplat.ops.composite_sample` stage (index range included)."""
    B, N = check_projected(proj, Ks)
    dtype, device = proj.amps.dtype, proj.amps.device
    feat = _tensor("features", features)
    if feat.dtype != dtype or feat.device != device:
        raise TypeError(f"features: expected {dtype} on {device} (as proj), got {feat.dtype} on {feat.device}")
    check_feature_shape(feat, B, N, "the cameras of proj")
    _finite("features", feat)
    if composite not in COMPOSITES:
        raise ValueError(f"composite: expected one of {COMPOSITES}, got {composite!r}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
    check_deterministic(deterministic)
    if not isinstance(indices, torch.Tensor) or indices.dtype != torch.int32 or indices.dim() != 4:
        got = f"{indices.dtype} {list(indices.shape)}" if isinstance(indices, torch.Tensor) else type(indices).__name__
        raise TypeError(f"indices: expected an int32 tensor [B,H,W,m], got {got}")
    if indices.device != device:
        raise ValueError(f"indices: expected device {device}, got {indices.device}")
    if indices.shape[0] != B or min(indices.shape[1:]) < 1:
        raise ValueError(f"indices: expected shape [B,H,W,m] with B={B} (the cameras of proj) and H, W, m >= 1, "
                         f"got {list(indices.shape)}")
    if values_checked() and indices.numel():  # few passes over [B,H,W,m]: they cost as much as the compositing
        lo, hi = torch.aminmax(indices)
        fail_if((lo < -1) | (hi >= N), lambda: f"indices: expected values in [-1, {N}) (-1 = empty slot, N={N} "
                f"points), got [{int(indices.min())}, {int(indices.max())}]")
    p = _tensor("probs", probs)
    if p.dtype != dtype or p.device != device or p.shape != indices.shape:
        raise ValueError(f"probs: expected shape {list(indices.shape)} and dtype {dtype} on {device}, "
                         f"got {list(p.shape)} {p.dtype} on {p.device}")
    if values_checked() and p.numel():
        lo, hi = torch.aminmax(p)  # NaN anywhere makes both NaN
        fail_if(~(lo.isfinite() & hi.isfinite()), lambda: "probs: contains NaN or Inf")
        fail_if((lo < 0) | (hi > 1) | (torch.where(indices >= 0, p, 1.0).amin() <= 0), lambda: "probs: expected "
                "inclusion probabilities in (0, 1] for filled slots and in [0, 1] for empty ones")
    if background is not None:
        _tensor("background", background)
        if background.dtype != dtype or background.device != device:
            raise TypeError(f"background: expected {dtype} on {device}, got {background.dtype} on {background.device}")
        _shape("background", background, (feat.shape[-1],), f"[C] with C={feat.shape[-1]}")
        _finite("background", background)
    _, H, W, m = indices.shape
    check_allocation(B=B, N=N, C=feat.shape[-1], width=W, height=H, samples=m, dtype=dtype, device=device,
                     what="composite")


def check_projection_numerics(*, huge: torch.Tensor, tiny: torch.Tensor, dtype: torch.dtype, lowpass: float,
                              differentiable: bool) -> None:
    """Refuse the float hazards of the projection instead of returning a silently wrong result.

    ``huge``, ``tiny``: ``[B, N]`` masks of the visible (in-range, not edge-on) splats whose screen covariance or
    centre overflows ``dtype``, and whose ``det Σ`` lies in ``(0, TINY_DET_F32)``.

    * A huge splat would be dropped silently (float32 from σ ≈ 10¹⁰ px): raise naming ``scales`` and the points.
    * float32 with ``lowpass < 1e-12``: a tiny splat (σ ≲ 10⁻⁵ px) has NaN/Inf gradients; raised only when the
      projection is differentiated.
    """
    def too_large() -> str:
        b, idx = _points(huge)
        return (f"scales: points {idx} (camera {b}) project to splats too large or too far off-screen "
                f"for {dtype} (the screen covariance or centre overflows) and would be dropped "
                f"silently; use float64, smaller scales, or cull them with near/far")

    def too_small() -> str:
        b, idx = _points(tiny)
        return (f"scales: points {idx} (camera {b}) are smaller than ~1e-5 px on screen with "
                f"lowpass={lowpass:g} (< 1e-12) in float32: their gradients would be NaN/Inf; use "
                f"lowpass >= 1e-12 or float64")

    with value_checks():
        fail_if(huge.any(), too_large)
        if differentiable and dtype == torch.float32 and lowpass < 1e-12:
            fail_if(tiny.any(), too_small)


def _points(mask: torch.Tensor, limit: int = 10) -> tuple[int, list[int]]:
    """First camera with a set entry of ``mask [B, N]`` and (up to ``limit``) point indices there."""
    b = int(torch.nonzero(mask.any(-1))[0, 0])
    return b, torch.nonzero(mask[b])[:limit, 0].tolist()
