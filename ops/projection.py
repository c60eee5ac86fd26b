"""Differentiable EWA projection of oriented surfels into each camera (pure PyTorch).

Conventions (docs/method.md): OpenCV camera (x right, y down, z forward), ``viewmats`` world→camera,
pixel centres at ``(i + 0.5, j + 0.5)``. A surfel ``k`` has tangent axes ``t0, t1`` from a
view-independent orthonormal frame of its normal (Duff et al. 2017), scaled by ``scales[k]``. The
local affine map of the tangent plane to the screen is the exact perspective Jacobian ``J`` (2×2,
scales included); the screen covariance is ``Σ = J Jᵀ + lowpass·I`` and the splat's alpha at pixel
``x`` is ``α(x) = min(α_max, A·exp(-½ (x-μ)ᵀ Σ⁻¹ (x-μ)))`` with the unit-peak amplitude
``A = o·|det J| / sqrt(det Σ)`` (``= o`` without low-pass).

Everything the per-pixel stages need is returned per camera and point; gradients flow back to the
surfel parameters and to ``viewmats``/``Ks`` through autograd.
"""
from __future__ import annotations

import dataclasses

import torch

from .validation import check_geometry, check_projection_numerics, check_range

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
        valid: ``[B,N]`` bool, the point is inside ``[near, far]`` and not exactly edge-on.
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
            lowpass: float) -> Projected:
    """Project surfels ``[N]`` into cameras ``[B]``; see the module docstring for the model.

    Args:
        means: ``[N,3]`` world positions. normals: ``[N,3]`` (normalised here).
        scales: ``[N,2]`` tangent std-devs (world units). opacities: ``[N]`` in [0, 1].
        viewmats: ``[B,4,4]`` world→camera. Ks: ``[B,3,3]`` intrinsics (pixels).
        near, far: clipping range on the centre depth. lowpass: screen-space low-pass variance (px²).

    Raises ``TypeError``/``ValueError`` naming the argument for invalid inputs (as :func:`nsplat.ops.splat`)
    and for the float hazards of ``ops/validation.py::check_projection_numerics``.
    """
    check_geometry(means, normals, scales, opacities, None, viewmats, Ks)
    check_range(near=near, far=far, lowpass=lowpass)
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    q = torch.einsum("bij,nj->bni", R, means) + t[:, None, :]
    n = normals / normals.norm(dim=-1, keepdim=True)
    t0, t1 = tangent_frame(n)
    T0 = torch.einsum("bij,nj->bni", R, t0 * scales[:, :1])
    T1 = torch.einsum("bij,nj->bni", R, t1 * scales[:, 1:])
    n_cam = torch.einsum("bij,nj->bni", R, n)

    z = q[..., 2]
    in_range = (z >= near) & (z <= far)
    zs = torch.where(in_range, z, torch.ones_like(z))
    # culled points: zero tangent axes and centre so that their discarded intermediates stay finite
    # (otherwise huge off-range coordinates can overflow float32 and poison the gradients with NaN)
    keep = in_range[..., None]
    T0 = torch.where(keep, T0, torch.zeros_like(T0))
    T1 = torch.where(keep, T1, torch.zeros_like(T1))
    q = torch.where(keep, q, torch.zeros_like(q))
    x_n, y_n = q[..., 0] / zs, q[..., 1] / zs
    K2 = Ks[:, None, :2, :2]
    uv = torch.stack([x_n, y_n], dim=-1)
    means2d = torch.einsum("bnij,bnj->bni", K2.expand(-1, q.shape[1], -1, -1), uv) + Ks[:, None, :2, 2]
    # d(x/z, y/z)/dX applied to the tangent axes, then K's 2x2 block.
    def dproj(T: torch.Tensor) -> torch.Tensor:
        return torch.stack([(T[..., 0] - x_n * T[..., 2]) / zs, (T[..., 1] - y_n * T[..., 2]) / zs], dim=-1)

    Jn = torch.stack([dproj(T0), dproj(T1)], dim=-1)  # [B,N,2,2], columns = tangent axes
    J = K2 @ Jn
    detJ = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    cov = J @ J.transpose(-1, -2)
    s00 = cov[..., 0, 0] + lowpass
    s01 = cov[..., 0, 1]
    s11 = cov[..., 1, 1] + lowpass
    det = s00 * s11 - s01 * s01
    grads = torch.is_grad_enabled() and any(t.requires_grad for t in (means, normals, scales, viewmats, Ks))
    check_projection_numerics(in_range=in_range, detJ=detJ, det=det, means2d=means2d, lowpass=float(lowpass),
                              differentiable=grads)
    valid = in_range & (detJ != 0) & (det > 0)
    dets = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([s11 / dets, -s01 / dets, s00 / dets], dim=-1)
    amps = torch.where(valid, opacities[None, :] * detJ.abs() / dets.sqrt(), torch.zeros_like(det))
    half_tr = 0.5 * (s00 + s11)
    sigma2 = half_tr + torch.sqrt(torch.clamp(half_tr * half_tr - dets, min=0.0))
    zero = torch.zeros_like
    return Projected(
        means2d=torch.where(valid[..., None], means2d, zero(means2d)),
        conics=torch.where(valid[..., None], conics, zero(conics)),
        amps=amps,
        normals_cam=n_cam,
        plane_offsets=(n_cam * q).sum(-1),
        depths=z,
        sigma2=torch.where(valid, sigma2, zero(sigma2)),
        valid=valid,
    )
