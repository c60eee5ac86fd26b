"""nsplat's surfel kernel in 3D Gaussian splatting's conventions and back: the amplitude, low-pass, opacity and
scale conversion of ``export --format 3dgs`` and of ``geometry.init: ply`` from a 3DGS file.

The two kernels at a pixel offset ``d`` from the projected centre, with ``J`` the 2×2 perspective Jacobian of
the surfel's scaled tangent axes (the same affine map in both renderers)::

    nsplat:  α = min(0.99,  o · κ · exp(−½ dᵀ(J Jᵀ + λ I)⁻¹ d)),   κ = |det J| / sqrt(det(J Jᵀ + λ I))
    3DGS:    α = min(0.999, o' · exp(−½ dᵀ(J' J'ᵀ + 0.3 I)⁻¹ d))

(λ: the run's ``render.lowpass``; 0.3: 3DGS's fixed screen dilation ``eps2d``; κ ≤ 1 is nsplat's low-pass
compensation, which keeps a splat's mass ``2π o |det J|`` independent of λ and dims sub-pixel splats.)

Exact when ``λ = 0.3``: the covariances agree with ``J' = J`` and the peaks with ``o' = o·κ``, but κ depends on
the view (on the splat's size in pixels) and a 3DGS file holds one opacity per Gaussian. The export therefore
writes the view-independent ``o' = min(0.99, o·κ̄)`` with ``κ̄`` the mean of κ over the training cameras that
see the splat (centre in the image and in front; a splat no camera sees keeps ``κ̄ = 1``); 0.99 is nsplat's
alpha clamp, so no exported Gaussian is more opaque than nsplat lets a splat be. For ``λ ≠ 0.3`` the tangent
variances also take the difference of the dilations, ``s'² = s² + (λ − 0.3)·p̄²`` with ``p̄`` the mean world
size of a pixel at the splat over the same cameras (exact for a surfel facing the camera; floored at
``(s/10)²``).

A rasteriser with Mip-Splatting's compensation (gsplat's ``antialiased``) multiplies the opacity by
``sqrt(det(J Jᵀ) / det(J Jᵀ + 0.3 I))`` in every view, which is κ at λ = 0.3: for it the export writes the
surfels' own opacities (:func:`antialiased_of_surfels`), exact in every view, and import takes them as they are.

Import inverts it: ``o = min(1 − 1e-6, o'/κ̄)`` with κ̄ of the imported surfel over the run's training cameras
and ``s² = s'² − (λ − 0.3)·p̄²``, so an export read back into the run it came from has its own opacities
wherever ``o·κ̄ < 0.99``.

What no per-Gaussian value can carry (measured in docs/results.md, "3DGS export"): κ's spread over the
views, nsplat's per-pixel ray–plane depth order (3DGS sorts by centre depth), the op's compositing of a
Poisson sample of ``m`` splats per pixel (3DGS composites every Gaussian above ``1/255``) and 3DGS's flat
axis, which :mod:`nsplat.gaussians.ply` writes as a thousandth of the larger tangent std-dev.
"""
from __future__ import annotations

import torch

from nsplat.ops.projection import project_torch

#: 3DGS's screen-space dilation (px²), added to every projected covariance by its rasteriser.
GS_LOWPASS = 0.3
#: nsplat's alpha clamp, the largest opacity an export writes.
ALPHA_MAX = 0.99
#: Largest imported opacity.
OPACITY_MAX = 1.0 - 1e-6


@torch.no_grad()
def view_statistics(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, viewmats: torch.Tensor,
                    Ks: torch.Tensor, width: int, height: int, *, lowpass: float, near: float = 0.01,
                    far: float = 1e10, chunk: int = 8) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-splat means over the cameras that see it of nsplat's peak factor κ and of the pixel's world size.

    Args:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]``: surfels. viewmats ``[V,4,4]`` OpenCV
        world→camera, Ks ``[V,3,3]``; width, height: the cameras' image size. lowpass: λ (px²).

    Returns:
        ``(kappa [N], pixel [N], seen [N])``: the mean κ (1 where no camera sees the splat), the mean
        ``depth / focal`` (world units per pixel; 0 where unseen) and the number of cameras that see it.
    """
    N = means.shape[0]
    dt = torch.float64
    m, n, s = means.to(dt), normals.to(dt), scales.to(dt)
    k_sum, p_sum, seen = m.new_zeros(N), m.new_zeros(N), m.new_zeros(N)
    ones = m.new_ones(N)
    for c in range(0, viewmats.shape[0], chunk):
        V, K = viewmats[c:c + chunk].to(dt), Ks[c:c + chunk].to(dt)
        p = project_torch(m, n, s, ones, V, K, near=near, far=far, lowpass=lowpass)
        x, y = p.means2d.unbind(-1)
        vis = p.valid & (x >= 0) & (x < width) & (y >= 0) & (y < height)
        f = torch.sqrt(K[:, 0, 0] * K[:, 1, 1])[:, None]
        k_sum += torch.where(vis, p.amps, 0.0).sum(0)
        p_sum += torch.where(vis, p.depths / f, 0.0).sum(0)
        seen += vis.to(dt).sum(0)
    some = seen > 0
    kappa = torch.where(some, k_sum / seen.clamp_min(1), 1.0)
    return kappa, torch.where(some, p_sum / seen.clamp_min(1), 0.0), seen


def to_gaussian(scales: torch.Tensor, opacities: torch.Tensor, kappa: torch.Tensor, pixel: torch.Tensor,
                lowpass: float) -> tuple[torch.Tensor, torch.Tensor]:
    """3DGS tangent std-devs ``[N,2]`` and opacities ``[N]`` of surfels ``scales [N,2]``, ``opacities [N]``
    rendered with low-pass ``lowpass``, given :func:`view_statistics`' ``kappa``, ``pixel`` (module docstring)."""
    var = scales.double() ** 2 + (lowpass - GS_LOWPASS) * pixel.double()[:, None] ** 2
    s = torch.sqrt(torch.maximum(var, 0.01 * scales.double() ** 2))
    return s, torch.clamp(opacities.double() * kappa.double(), max=ALPHA_MAX)


def from_gaussian(scales: torch.Tensor, opacities: torch.Tensor, kappa: torch.Tensor, pixel: torch.Tensor,
                  lowpass: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The inverse of :func:`to_gaussian`: surfel std-devs ``[N,2]`` and opacities ``[N]`` of 3DGS tangent
    std-devs and opacities (``kappa``, ``pixel`` of the surfels: :func:`view_statistics` of the result, see
    :func:`surfels_of_gaussians`)."""
    var = scales.double() ** 2 - (lowpass - GS_LOWPASS) * pixel.double()[:, None] ** 2
    s = torch.sqrt(torch.maximum(var, 0.01 * scales.double() ** 2))
    return s, torch.clamp(opacities.double() / kappa.double(), max=OPACITY_MAX)


def antialiased_of_surfels(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor,
                           opacities: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                           *, lowpass: float, near: float = 0.01, far: float = 1e10) -> tuple[torch.Tensor,
                                                                                              torch.Tensor]:
    """3DGS tangent std-devs ``[N,2]`` and opacities ``[N]`` (float64) of surfels for a rasteriser with
    Mip-Splatting's compensation (``antialiased``): its per-view factor is nsplat's κ at 0.3 px², so with
    ``lowpass`` 0.3 they are the surfels' own, ``o' = min(0.99, o)`` and ``s' = s``, exact in every view. Other
    low-passes: ``s'`` as :func:`to_gaussian` and ``o' = min(0.99, o·κ̄/κ̄')``, κ̄ the surfels' mean κ and κ̄'
    the Gaussians' mean compensation over the cameras (shapes as :func:`view_statistics`)."""
    if lowpass == GS_LOWPASS:
        return scales.double(), torch.clamp(opacities.double(), max=ALPHA_MAX)
    kw = dict(near=near, far=far)
    kappa, pixel, _ = view_statistics(means, normals, scales, viewmats, Ks, width, height, lowpass=lowpass, **kw)
    s, _ = to_gaussian(scales, opacities, kappa, pixel, lowpass)
    kappa_gs, _, _ = view_statistics(means, normals, s, viewmats, Ks, width, height, lowpass=GS_LOWPASS, **kw)
    return s, torch.clamp(opacities.double() * kappa / kappa_gs, max=ALPHA_MAX)


def surfels_of_gaussians(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                         viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *, lowpass: float,
                         near: float = 0.01, far: float = 1e10,
                         antialiased: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """nsplat std-devs ``[N,2]`` and opacities ``[N]`` (float64) of 3DGS Gaussians read as surfels (``means
    [N,3]``, ``normals [N,3]``, tangent ``scales [N,2]``, ``opacities [N]``: :func:`nsplat.gaussians.ply.
    read_gaussian_ply`), for cameras ``viewmats [V,4,4]``, ``Ks [V,3,3]`` of ``width × height`` and nsplat's
    low-pass ``lowpass``: :func:`from_gaussian` with κ̄ of the converted surfels (the pixel size does not
    depend on the std-devs, so two passes of :func:`view_statistics` solve it exactly).

    ``antialiased`` (a file for Mip-Splatting's compensation): the compensation is folded into the opacity,
    ``o = min(1 − 1e-6, o'·κ̄'/κ̄)`` with κ̄' the Gaussians' mean compensation (κ at 0.3 px²) and κ̄ the surfels';
    with ``lowpass`` 0.3 that is the file's own opacity."""
    kw = dict(near=near, far=far)
    if antialiased and lowpass == GS_LOWPASS:
        return scales.double(), torch.clamp(opacities.double(), max=OPACITY_MAX)
    kappa_gs, pixel, _ = view_statistics(means, normals, scales, viewmats, Ks, width, height, lowpass=GS_LOWPASS, **kw)
    s, _ = from_gaussian(scales, opacities, torch.ones_like(pixel), pixel, lowpass)
    kappa, _, _ = view_statistics(means, normals, s, viewmats, Ks, width, height, lowpass=lowpass, **kw)
    return from_gaussian(scales, opacities * kappa_gs if antialiased else opacities, kappa, pixel, lowpass)
