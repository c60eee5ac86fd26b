"""Second-order spherical-harmonics (SH) irradiance shading of per-point albedo.

Basis: the real, orthonormal SH ``Y_lm`` on the unit sphere (``∫ Y_lm Y_l'm' dω = δ``) up to
``l = 2``, in the order ``(0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), (2,0), (2,1), (2,2)``, of
a unit world-space normal ``n = (x, y, z)``::

    Y_00 = 1/(2√π)                 = 0.282095
    Y_1-1 = √(3/4π)·y, Y_10 = √(3/4π)·z, Y_11 = √(3/4π)·x          (√(3/4π) = 0.488603)
    Y_2-2 = ½√(15/π)·xy, Y_2-1 = ½√(15/π)·yz, Y_21 = ½√(15/π)·xz      (½√(15/π) = 1.092548)
    Y_20 = ¼√(5/π)·(3z² − 1)                                         (¼√(5/π) = 0.315392)
    Y_22 = ¼√(15/π)·(x² − y²)                                        (¼√(15/π) = 0.546274)

Lighting: the 9 coefficients ``L_lm`` per colour channel of the distant incident radiance
``L(ω) = Σ L_lm Y_lm(ω)``. Irradiance of a surface with normal ``n`` (Ramamoorthi & Hanrahan 2001,
exact for this band-limited ``L`` when no clamping of the cosine lobe beyond ``l = 2`` matters)::

    E(n) = Σ_lm Â_l L_lm Y_lm(n),   Â_0 = π, Â_1 = 2π/3, Â_2 = π/4

and a Lambertian point with albedo ``a`` leaves radiance ``B = a · E(n) / π`` (clamped at 0 when
``clamp`` is set). Hand check: a uniform unit-radiance sky, ``L_00 = √(4π)`` and the rest 0, gives
``E = π·√(4π)·1/(2√π) = π`` and ``B = a`` for every normal. :class:`SHLighting` starts there (scaled
by ``ambient``), so an un-optimised scene renders its albedo.
"""
from __future__ import annotations

import math

import torch

from nsplat.ops.library import view_colour_op

#: Normalisation constants of the real SH basis (see the module docstring).
_C0 = 0.5 / math.sqrt(math.pi)
_C1 = math.sqrt(3.0 / (4.0 * math.pi))
_C2 = 0.5 * math.sqrt(15.0 / math.pi)
_C20 = 0.25 * math.sqrt(5.0 / math.pi)
_C22 = 0.25 * math.sqrt(15.0 / math.pi)
#: Cosine-lobe convolution factors Â_l for the 9 coefficients, in basis order.
BAND_FACTORS = (math.pi,) + (2.0 * math.pi / 3.0,) * 3 + (math.pi / 4.0,) * 5


def sh_basis(normals: torch.Tensor) -> torch.Tensor:
    """Real orthonormal SH basis up to l = 2 of unit directions ``normals [..., 3]`` → ``[..., 9]``.

    The input is normalised here; order as in the module docstring.
    """
    n = torch.nn.functional.normalize(normals, dim=-1)
    x, y, z = n.unbind(-1)
    return torch.stack([
        torch.full_like(x, _C0),
        _C1 * y, _C1 * z, _C1 * x,
        _C2 * x * y, _C2 * y * z, _C20 * (3.0 * z * z - 1.0), _C2 * x * z, _C22 * (x * x - y * y),
    ], dim=-1)


def sh_irradiance(normals: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Irradiance ``E(n) [..., C]`` of unit normals ``[..., 3]`` under SH radiance ``coeffs [9, C]``."""
    if coeffs.shape[0] != 9 or coeffs.dim() != 2:
        raise ValueError(f"coeffs must be [9, C], got {tuple(coeffs.shape)}")
    a = torch.tensor(BAND_FACTORS, dtype=coeffs.dtype, device=coeffs.device)
    return sh_basis(normals).to(coeffs.dtype) @ (a[:, None] * coeffs)


def sh_shade(albedo: torch.Tensor, normals: torch.Tensor, coeffs: torch.Tensor,
             clamp: bool = True) -> torch.Tensor:
    """Lambertian radiance ``albedo · E(n) / π``: albedo ``[N, C]``, normals ``[N, 3]``, coeffs
    ``[9, C]`` → ``[N, C]`` (irradiance clamped at 0 if ``clamp``)."""
    if albedo.shape[-1] != coeffs.shape[-1]:
        raise ValueError(f"albedo has {albedo.shape[-1]} channels but coeffs has {coeffs.shape[-1]}")
    e = sh_irradiance(normals, coeffs)
    if clamp:
        e = e.clamp_min(0.0)
    return albedo * e / math.pi


class SHLighting(torch.nn.Module):
    """Learnable 2nd-order SH lighting: ``coeffs [9, C]`` (9 per channel).

    Args:
        channels: colour channels C.
        ambient: initial uniform radiance (``L_00 = ambient·√(4π)``, others 0), so that the initial
            shading multiplies albedo by ``ambient``.
        clamp: clamp the irradiance at 0.
        learnable: make the coefficients a parameter (else a buffer).
    """

    def __init__(self, channels: int = 3, ambient: float = 1.0, clamp: bool = True,
                 learnable: bool = True) -> None:
        super().__init__()
        c = torch.zeros(9, channels)
        c[0] = ambient * math.sqrt(4.0 * math.pi)
        self.clamp = clamp
        if learnable:
            self.coeffs = torch.nn.Parameter(c)
        else:
            self.register_buffer("coeffs", c)

    def forward(self, albedo: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """Shaded colours ``[N, C]`` of points with albedo ``[N, C]`` and normals ``[N, 3]``."""
        return sh_shade(albedo, normals, self.coeffs, clamp=self.clamp)


# ------------------------------------------------------------------------------ view-dependent colour
#: Real SH normalisation constants of band 3 (orders m = -3..3), for view directions.
_C3 = (0.25 * math.sqrt(35.0 / (2.0 * math.pi)), 0.5 * math.sqrt(105.0 / math.pi),
       0.25 * math.sqrt(21.0 / (2.0 * math.pi)), 0.25 * math.sqrt(7.0 / math.pi))
#: Largest SH degree of the view-dependent colour.
MAX_VIEW_DEGREE = 3


def view_channels(degree: int) -> int:
    """Feature channels of an RGB colour with view-dependent SH up to ``degree``: ``3·(degree+1)²``."""
    if not 0 <= degree <= MAX_VIEW_DEGREE:
        raise ValueError(f"degree: expected 0..{MAX_VIEW_DEGREE}, got {degree}")
    return 3 * (degree + 1) ** 2


def sh_view_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real orthonormal SH basis of unit directions ``dirs [..., 3]`` up to ``degree`` (≤ 3) without the
    constant band: ``[..., (degree+1)² − 1]``, orders ``(1,-1), (1,0), (1,1), (2,-2) … (3,3)``."""
    x, y, z = dirs.unbind(-1)
    out: list[torch.Tensor] = []
    if degree >= 1:
        out += [_C1 * y, _C1 * z, _C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_C2 * x * y, _C2 * y * z, _C20 * (3.0 * zz - 1.0), _C2 * x * z, _C22 * (xx - yy)]
    if degree >= 3:
        out += [_C3[0] * y * (3.0 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (5.0 * zz - 1.0),
                _C3[3] * z * (5.0 * zz - 3.0), _C3[2] * x * (5.0 * zz - 1.0), 0.5 * _C3[1] * z * (xx - yy),
                _C3[0] * x * (xx - 3.0 * yy)]
    return torch.stack(out, dim=-1) if out else dirs.new_zeros(dirs.shape[:-1] + (0,))


def view_colour(features: torch.Tensor, means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """RGB of points seen from one camera (the model of :func:`view_colour_torch`; shapes there). On the CPU and
    CUDA with degree >= 1 the native kernel (``nsplat::view_colour``) computes it, elsewhere
    :func:`view_colour_torch`."""
    K = features.shape[-1] // 3
    degree = math.isqrt(K) - 1
    if features.shape[-1] != view_channels(degree):
        raise ValueError(f"features: expected 3·(L+1)² channels (3, 12, 27 or 48), got {features.shape[-1]}")
    dtypes = {features.dtype, means.dtype, viewmat.dtype}
    native_device = features.device.type in ("cpu", "cuda")
    if degree == 0 or not native_device or len(dtypes) > 1 or dtypes - {torch.float32, torch.float64}:
        return view_colour_torch(features, means, viewmat)
    return view_colour_op(features, means, viewmat, degree)


def view_colour_torch(features: torch.Tensor, means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """RGB of points seen from one camera: ``max(0, f_0 + Σ_{l≥1} f_lm · Y_lm(d))``.

    Args:
        features: ``[N, 3·(L+1)²]``: channels ``3j..3j+2`` are the RGB coefficient of basis function ``j``;
            ``j = 0`` is the view-independent colour itself (the constant ``Y_00`` folded in), so
            ``features[:, :3]`` is the point's mean colour and a degree-0 scene is plain RGB.
        means: ``[N,3]`` world positions. viewmat: ``[4,4]`` world→camera (the camera centre is
            ``−Rᵀt``); ``d`` is the unit direction from the camera centre to the point.

    Returns:
        ``[N,3]`` colours, clamped at 0 (not above: the op composites any value).
    """
    K = features.shape[-1] // 3
    degree = math.isqrt(K) - 1
    if features.shape[-1] != view_channels(degree):
        raise ValueError(f"features: expected 3·(L+1)² channels (3, 12, 27 or 48), got {features.shape[-1]}")
    if degree == 0:
        return features.clamp_min(0.0)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    d = torch.nn.functional.normalize(means - (-(R.T @ t)), dim=-1)
    basis = sh_view_basis(d, degree)                                     # [N, K-1]
    rest = features[:, 3:].reshape(-1, K - 1, 3)
    return (features[:, :3] + (basis[..., None] * rest).sum(1)).clamp_min(0.0)
