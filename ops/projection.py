"""Differentiable EWA projection of oriented surfels into each camera (pure PyTorch).

Conventions (docs/method.md): OpenCV camera (x right, y down, z forward), ``viewmats`` world→camera,
pixel centres at ``(i + 0.5, j + 0.5)``. A surfel ``k`` has tangent axes ``t0, t1`` from a
view-independent orthonormal frame of its normal (Duff et al. 2017), scaled by ``scales[k]``. The
local affine map of the tangent plane to the screen is the exact perspective Jacobian ``J`` (2×2,
scales included); the screen covariance is ``Σ = J Jᵀ + lowpass·I`` and the splat's alpha at pixel
``x`` is ``α(x) = min(α_max, A·exp(-½ (x-μ)ᵀ Σ⁻¹ (x-μ)))`` with the unit-peak amplitude
``A = o·|det J| / sqrt(det Σ)`` (``= o`` without low-pass). Surfels are two-sided unless
``backface_cull``: then a surfel whose normal faces away from the camera (``n_c · q ≥ 0``, classic surface
splatting's back-face culling) is culled in that camera like a point outside ``[near, far]``.

Everything the per-pixel stages need is returned per camera and point; gradients flow back to the
surfel parameters and to ``viewmats``/``Ks`` through autograd.
"""
from __future__ import annotations

import dataclasses

import torch

from .fixed_order import expand_fixed
from .library import project_op
from .validation import TINY_DET_F32, check_geometry, check_projection_numerics, check_range, values_checked
from .value_checks import value_checks

ALPHA_MAX = 0.99
#: A ray whose cosine with a splat's plane normal is below this uses the splat's centre depth.
PARALLEL_COS = 1e-2


@dataclasses.dataclass
class Projected:
    """Per-camera projected surfels, all ``[B, N, ...]``.

    Attributes:
        means2d: ``[B,N,2]`` screen-space centres μ (pixels).
        conics: ``[B,N,3]`` inverse covariance ``(a, b, c)`` with ``Σ⁻¹ = [[a, b], [b, c]]``.
        amps: ``[B,N]`` unit-peak amplitude ``A`` (0 for culled points).
        normals_cam: ``[B,N,3]`` unit normal in camera coordinates.
        plane_offsets: ``[B,N]`` ``n_c · q`` (plane equation ``n_c · X = n_c · q``).
        depths: ``[B,N]`` centre depth ``q_z``.
        sigma2: ``[B,N]`` largest eigenvalue of ``Σ`` (px²), for the sampler's isotropic majorant.
        valid: ``[B,N]`` bool, the point is inside ``[near, far]``, not exactly edge-on and (with
            ``backface_cull``) faces the camera.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    amps: torch.Tensor
    normals_cam: torch.Tensor
    plane_offsets: torch.Tensor
    depths: torch.Tensor
    sigma2: torch.Tensor
    valid: torch.Tensor


def tangent_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal tangent axes of unit normals ``n [..., 3]`` (Duff et al. 2017 construction).

    Returns ``(t0, t1)``, each ``[..., 3]``, with ``t0 × t1 = n``. The frame depends only on the
    normal (not on the camera), so anisotropic scales are view independent.
    """
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t0 = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    t1 = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t0, t1


def pixel_rays(Ks: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Camera-space rays ``K⁻¹ [u, v, 1]`` through pixel centres: ``[B, H, W, 3]`` with z = 1."""
    B = Ks.shape[0]
    dtype, device = Ks.dtype, Ks.device
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                          torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(1, -1, 3).expand(B, -1, -1)
    rays = torch.linalg.solve_triangular(Ks, pix.transpose(1, 2), upper=True).transpose(1, 2)
    return rays.reshape(B, height, width, 3)


def project(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
            viewmats: torch.Tensor, Ks: torch.Tensor, *, near: float, far: float,
            lowpass: float, backface_cull: bool = False) -> Projected:
    """Project surfels ``[N]`` into cameras ``[B]``; see the module docstring for the model.

    Args:
        means: ``[N,3]`` world positions. normals: ``[N,3]`` (normalised here).
        scales: ``[N,2]`` tangent std-devs (world units). opacities: ``[N]`` in [0, 1].
        viewmats: ``[B,4,4]`` world→camera. Ks: ``[B,3,3]`` intrinsics (pixels).
        near, far: clipping range on the centre depth. lowpass: screen-space low-pass variance (px²).
        backface_cull: cull, per camera, the surfels whose normal faces away from it (``n_c · q ≥ 0``). The
            cut is a hard decision (no gradient across it, like the ``near`` plane).

    Raises ``TypeError``/``ValueError`` naming the argument for invalid inputs (as :func:`nsplat.ops.splat`)
    and for the float hazards of ``ops/validation.py::check_projection_numerics``.
    """
    with value_checks():
        check_geometry(means, normals, scales, opacities, None, viewmats, Ks)
        check_range(near=near, far=far, lowpass=lowpass)
    return project_checked(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass,
                           backface_cull=backface_cull)


def project_checked(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                    viewmats: torch.Tensor, Ks: torch.Tensor, *, near: float, far: float,
                    lowpass: float, backface_cull: bool = False) -> Projected:
    """:func:`project` on arguments the caller has already validated (``nsplat.ops.splat`` does): the checks of
    the inputs are skipped, the float hazards of the computation (``check_projection_numerics``) still raise.
    On the CPU and CUDA the native kernel (``nsplat::project``) computes it, elsewhere :func:`project_torch`."""
    if means.device.type not in ("cpu", "cuda"):
        return project_torch(means, normals, scales, opacities, viewmats, Ks, near=near, far=far, lowpass=lowpass,
                             backface_cull=backface_cull)
    m2, conics, amps, ncam, off, depths, sigma2, valid, hazard = project_op(
        means, normals, scales, opacities, viewmats, Ks, float(near), float(far), float(lowpass), bool(backface_cull))
    if values_checked():
        grads = torch.is_grad_enabled() and any(x.requires_grad for x in (means, normals, scales, viewmats, Ks))
        check_projection_numerics(huge=hazard == 1, tiny=hazard == 2, dtype=means.dtype, lowpass=float(lowpass),
                                  differentiable=grads)
    return Projected(means2d=m2, conics=conics, amps=amps, normals_cam=ncam, plane_offsets=off, depths=depths,
                     sigma2=sigma2, valid=valid)


def project_torch(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                  viewmats: torch.Tensor, Ks: torch.Tensor, *, near: float, far: float,
                  lowpass: float, backface_cull: bool = False) -> Projected:
    """The projection in pure PyTorch (autograd; any device): the reference of the native CPU kernel and the
    path of the other devices. Arguments as :func:`project`, unchecked."""
    # Element-wise arithmetic only, on [B,N] operands made explicit by expand_fixed: no matmul, einsum
    # or sum whose rounding would depend on the thread count or the CPU's vector width (fixed_order.py).
    B, N = viewmats.shape[0], means.shape[0]
    nx, ny, nz = normals.unbind(-1)
    norm = torch.sqrt(nx * nx + ny * ny + nz * nz)
    n = torch.stack([nx / norm, ny / norm, nz / norm], dim=-1)
    t0, t1 = tangent_frame(n)
    s0, s1 = scales.unbind(-1)
    per_point = torch.stack([*means.unbind(-1), *n.unbind(-1), *(c * s0 for c in t0.unbind(-1)),
                             *(c * s1 for c in t1.unbind(-1)), opacities], dim=-1)
    P = expand_fixed(per_point, 0, B).unbind(-1)                                 # 13 x [B,N]
    C = expand_fixed(torch.cat([viewmats[:, :3, :].reshape(B, 12), Ks.reshape(B, 9)], dim=-1), 1, N).unbind(-1)
    k00, k01, cx, k10, k11, cy = C[12:18]

    def rotate(v: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
        return [C[4 * i] * v[0] + C[4 * i + 1] * v[1] + C[4 * i + 2] * v[2] for i in range(3)]

    q = [c + C[4 * i + 3] for i, c in enumerate(rotate(P[0:3]))]
    n_cam = rotate(P[3:6])
    T0 = rotate(P[6:9])
    T1 = rotate(P[9:12])
    opac = P[12]

    z = q[2]
    in_range = (z >= near) & (z <= far)
    zs = torch.where(in_range, z, torch.ones_like(z))
    # culled points: zero tangent axes and centre so that their discarded intermediates stay finite
    # (otherwise huge off-range coordinates can overflow float32 and poison the gradients with NaN)
    zero = torch.zeros_like(z)
    T0 = [torch.where(in_range, c, zero) for c in T0]
    T1 = [torch.where(in_range, c, zero) for c in T1]
    q = [torch.where(in_range, c, zero) for c in q]
    x_n, y_n = q[0] / zs, q[1] / zs
    means2d = torch.stack([k00 * x_n + k01 * y_n + cx, k10 * x_n + k11 * y_n + cy], dim=-1)

    # d(x/z, y/z)/dX applied to the tangent axes (columns of Jn), then K's 2x2 block.
    def dproj(T: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        return (T[0] - x_n * T[2]) / zs, (T[1] - y_n * T[2]) / zs

    (a0, a1), (b0, b1) = dproj(T0), dproj(T1)                                   # Jn = [[a0, b0], [a1, b1]]
    j00, j01 = k00 * a0 + k01 * a1, k00 * b0 + k01 * b1
    j10, j11 = k10 * a0 + k11 * a1, k10 * b0 + k11 * b1
    detJ = j00 * j11 - j01 * j10
    s00 = (j00 * j00 + j01 * j01) + lowpass
    s01 = j00 * j10 + j01 * j11
    s11 = (j10 * j10 + j11 * j11) + lowpass
    det = s00 * s11 - s01 * s01
    if values_checked():
        grads = torch.is_grad_enabled() and any(x.requires_grad for x in (means, normals, scales, viewmats, Ks))
        live = in_range & (detJ != 0)
        huge = live & ~(torch.isfinite(det) & torch.isfinite(detJ) & torch.isfinite(means2d).all(-1))
        tiny = live & (det > 0) & (det < TINY_DET_F32)
        check_projection_numerics(huge=huge, tiny=tiny, dtype=det.dtype, lowpass=float(lowpass), differentiable=grads)
    plane_offsets = n_cam[0] * q[0] + n_cam[1] * q[1] + n_cam[2] * q[2]
    valid = in_range & (detJ != 0) & (det > 0)
    if backface_cull:
        valid = valid & (plane_offsets.detach() < 0)
    dets = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([s11 / dets, -s01 / dets, s00 / dets], dim=-1)
    amps = torch.where(valid, opac * detJ.abs() / dets.sqrt(), torch.zeros_like(det))
    half_tr = 0.5 * (s00 + s11)
    sigma2 = half_tr + torch.sqrt(torch.clamp(half_tr * half_tr - dets, min=0.0))
    return Projected(
        means2d=torch.where(valid[..., None], means2d, torch.zeros_like(means2d)),
        conics=torch.where(valid[..., None], conics, torch.zeros_like(conics)),
        amps=amps,
        normals_cam=torch.stack(n_cam, dim=-1),
        plane_offsets=plane_offsets,
        depths=z,
        sigma2=torch.where(valid, sigma2, torch.zeros_like(sigma2)),
        valid=valid,
    )
