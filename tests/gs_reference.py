"""A 3D Gaussian splatting reference renderer (pure PyTorch, CPU), used only to check what 3DGS viewers show
of ``export --format 3dgs`` files (and of 3DGS files nsplat imports).

Written from the image formation of Kerbl et al. 2023 ("3D Gaussian Splatting for Real-Time Radiance Field
Rendering", §4 and §6) as its rasteriser implements it; nothing here is nsplat's kernel:

* **Gaussian**: ``Σ = R S Sᵀ Rᵀ`` with ``S = diag(exp(scale_i))`` and ``R`` the rotation of the unit
  quaternion ``(w, x, y, z)`` (stored unnormalised); opacity ``sigmoid(opacity)``.
* **Projection** (EWA, Zwicker et al. 2002): camera-space centre ``t = W μ + w``; the affine approximation of
  the perspective projection at ``t``, ``J = [[fx/t_z, 0, −fx t_x/t_z²], [0, fy/t_z, −fy t_y/t_z²]]`` (with
  ``t_x/t_z``, ``t_y/t_z`` clamped to 1.3× the half field of view, as the rasteriser does);
  ``Σ' = J W Σ Wᵀ Jᵀ + eps2d·I`` with ``eps2d = 0.3`` px² (the rasteriser's low-pass dilation; no amplitude
  compensation unless ``antialiased``, Mip-Splatting's ``sqrt(det Σ'₀ / det Σ')``). Gaussians with
  ``t_z`` below ``near`` are culled, as are those whose ``3σ`` square (radius ``ceil(3·sqrt(λ_max(Σ')))``)
  misses the image.
* **Colour**: degree-3 real SH with 3DGS's basis signs, evaluated in the direction from the camera centre to
  the Gaussian's centre: ``max(0, ½ + Σ_j Y'_j(d) c_j)``.
* **Blending** (per 16×16 tile, over the Gaussians whose 3σ square touches the tile, sorted by centre depth
  ``t_z``, nearest first): ``α = min(alpha_clamp, o·exp(−½ dᵀΣ'⁻¹d))`` at the pixel centre ``(i+½, j+½)``;
  ``α < 1/255`` is skipped; front to back ``C += c α T``, ``T ← T(1 − α)``, stopping *before* a Gaussian
  that would take ``T`` below ``1e-4``; the image is ``C + T·background``.
"""
from __future__ import annotations

import math

import torch

#: 3DGS's SH constants (``utils/sh_utils.py`` of the reference code; the basis with its signs).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)
EPS2D = 0.3
TILE = 16


def sh_to_rgb(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """3DGS's colour ``[N,3]`` of SH coefficients ``sh [N,K,3]`` (``K = (L+1)²``, ``L ≤ 3``; ``sh[:,0]`` is
    ``f_dc``) seen along unit directions ``dirs [N,3]``."""
    K = sh.shape[1]
    x, y, z = (dirs[:, i:i + 1] for i in range(3))
    out = SH_C0 * sh[:, 0]
    if K > 1:
        out = out - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if K > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out = (out + SH_C2[0] * xy * sh[:, 4] + SH_C2[1] * yz * sh[:, 5] + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
               + SH_C2[3] * xz * sh[:, 7] + SH_C2[4] * (xx - yy) * sh[:, 8])
    if K > 9:
        out = (out + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9] + SH_C3[1] * xy * z * sh[:, 10]
               + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
               + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + SH_C3[5] * z * (xx - yy) * sh[:, 14]
               + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15])
    return torch.clamp_min(out + 0.5, 0.0)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[N,3,3]`` of quaternions ``q [N,4]`` ``(w, x, y, z)`` (normalised here)."""
    w, x, y, z = torch.nn.functional.normalize(q, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def gaussians_of_ply(path: str) -> dict[str, torch.Tensor | bool]:
    """The raw 3DGS parameters of a ``point_cloud.ply`` (float64): ``means [N,3]``, ``quats [N,4]``,
    ``log_scales [N,3]``, ``opacity_logits [N]``, ``sh [N,K,3]``; and ``antialiased``: whether the header has
    the comment ``SplatRenderMode: mip`` (gsplat's and Brush's mark of a file for the antialiased mode)."""
    import numpy as np
    from plyfile import PlyData
    ply = PlyData.read(str(path))
    v = ply["vertex"]
    names = v.data.dtype.names

    def cols(keys):
        return torch.from_numpy(np.stack([np.asarray(v[k], np.float64) for k in keys], 1))

    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    N = v.count
    f_dc = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    f_rest = cols(rest).reshape(N, 3, len(rest) // 3).transpose(1, 2) if rest else f_dc.new_zeros(N, 0, 3)
    return {"means": cols(["x", "y", "z"]), "quats": cols([f"rot_{i}" for i in range(4)]),
            "log_scales": cols([f"scale_{i}" for i in range(3)]), "opacity_logits": cols(["opacity"])[:, 0],
            "sh": torch.cat([f_dc[:, None], f_rest], 1),
            "antialiased": any(c.strip().lower() == "splatrendermode: mip" for c in ply.comments)}


@torch.no_grad()
def render_3dgs(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacity_logits: torch.Tensor,
                sh: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                background: torch.Tensor, *, near: float = 0.01, eps2d: float = EPS2D, alpha_clamp: float = 0.999,
                antialiased: bool = False, min_alpha: float = 1.0 / 255.0, min_transmittance: float = 1e-4,
                cull: bool = True) -> torch.Tensor:
    """Render Gaussians into one camera as 3DGS does (module docstring); returns the image ``[H,W,3]``.

    Args:
        means ``[N,3]``, quats ``[N,4]`` (w, x, y, z), log_scales ``[N,3]``, opacity_logits ``[N]``, sh
        ``[N,K,3]``: the file's values. viewmat ``[4,4]`` OpenCV world→camera, K ``[3,3]`` pixels.
        background ``[3]``. alpha_clamp: 0.99 (the original rasteriser) or 0.999 (gsplat).
        min_alpha, min_transmittance, cull: the rasteriser's shortcuts (skip ``α < 1/255``, stop below
            ``T = 1e-4``, only the tiles of the 3σ square); ``0, 0, False`` turns them off (the exact blend
            of every Gaussian, for checks of the kernel alone).
    """
    dt = torch.float64
    means, quats, log_scales, sh = means.to(dt), quats.to(dt), log_scales.to(dt), sh.to(dt)
    Wr, w = viewmat[:3, :3].to(dt), viewmat[:3, 3].to(dt)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    t = means @ Wr.T + w
    keep = t[:, 2] > near
    R = quat_to_rotmat(quats)
    M = R * torch.exp(log_scales)[:, None, :]
    cov3 = M @ M.transpose(1, 2)
    tz = t[:, 2].clamp_min(near)
    lim_x, lim_y = 1.3 * (0.5 * width / fx), 1.3 * (0.5 * height / fy)
    tx = (t[:, 0] / tz).clamp(-lim_x, lim_x) * tz
    ty = (t[:, 1] / tz).clamp(-lim_y, lim_y) * tz
    J = torch.zeros(t.shape[0], 2, 3, dtype=dt)
    J[:, 0, 0], J[:, 0, 2] = fx / tz, -fx * tx / tz**2
    J[:, 1, 1], J[:, 1, 2] = fy / tz, -fy * ty / tz**2
    T = J @ Wr
    cov2 = T @ cov3 @ T.transpose(1, 2)
    det0 = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2
    cov2 = cov2 + eps2d * torch.eye(2, dtype=dt)
    det = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2
    keep &= det > 0
    det = torch.where(keep, det, torch.ones_like(det))
    opac = torch.sigmoid(opacity_logits.to(dt))
    if antialiased:
        opac = opac * torch.sqrt(torch.clamp_min(det0, 0.0) / det)
    conic = torch.stack([cov2[:, 1, 1] / det, -cov2[:, 0, 1] / det, cov2[:, 0, 0] / det], -1)
    mid = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
    radius = torch.ceil(3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))))
    mu = torch.stack([fx * t[:, 0] / tz + cx, fy * t[:, 1] / tz + cy], -1)
    if cull:
        keep &= ((mu[:, 0] + radius > 0) & (mu[:, 0] - radius < width) & (mu[:, 1] + radius > 0)
                 & (mu[:, 1] - radius < height))
    campos = -Wr.T @ w
    dirs = torch.nn.functional.normalize(means - campos, dim=-1)
    colour = sh_to_rgb(sh, dirs)

    idx = torch.nonzero(keep)[:, 0]
    idx = idx[torch.argsort(t[idx, 2], stable=True)]                    # nearest first
    mu, conic, opac, colour, radius = mu[idx], conic[idx], opac[idx], colour[idx], radius[idx]
    # the rasteriser's tile rectangle of each Gaussian: tiles [lo, hi) per axis
    lo = torch.stack([((mu[:, i] - radius) / TILE).floor().clamp(0, n) for i, n in
                      ((0, math.ceil(width / TILE)), (1, math.ceil(height / TILE)))], -1)
    hi = torch.stack([((mu[:, i] + radius + TILE - 1) / TILE).floor().clamp(0, n) for i, n in
                      ((0, math.ceil(width / TILE)), (1, math.ceil(height / TILE)))], -1)
    bg = background.to(dt)
    image = bg.expand(height, width, 3).clone()
    for ty_ in range(math.ceil(height / TILE)):
        for tx_ in range(math.ceil(width / TILE)):
            sel = (lo[:, 0] <= tx_) & (tx_ < hi[:, 0]) & (lo[:, 1] <= ty_) & (ty_ < hi[:, 1]) if cull \
                else torch.ones_like(radius, dtype=torch.bool)
            x0, y0 = tx_ * TILE, ty_ * TILE
            x1, y1 = min(x0 + TILE, width), min(y0 + TILE, height)
            if not bool(sel.any()):
                continue
            v, u = torch.meshgrid(torch.arange(y0, y1, dtype=dt) + 0.5, torch.arange(x0, x1, dtype=dt) + 0.5,
                                  indexing="ij")
            pix = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
            d = pix[:, None, :] - mu[sel][None]                             # [P, n, 2]
            c = conic[sel]
            power = -0.5 * (c[:, 0] * d[..., 0] ** 2 + c[:, 2] * d[..., 1] ** 2) - c[:, 1] * d[..., 0] * d[..., 1]
            alpha = torch.clamp_max(opac[sel] * torch.exp(power), alpha_clamp)
            alpha = torch.where((power <= 0) & (alpha >= min_alpha), alpha, torch.zeros_like(alpha))
            trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha], 1), 1)
            stop = (trans[:, 1:] < min_transmittance) & (alpha > 0)          # this Gaussian would end the pixel
            used = torch.cumsum(stop.to(torch.int64), 1) == 0
            wgt = alpha * trans[:, :-1] * used
            t_end = torch.where(used, 1.0 - alpha, torch.ones_like(alpha)).prod(1, keepdim=True)
            out = wgt @ colour[sel] + t_end * bg
            image[y0:y1, x0:x1] = out.reshape(y1 - y0, x1 - x0, 3)
    return image
