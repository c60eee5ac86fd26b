"""Dense RGB-D registration of a frame to a surfel model: Gauss-Newton on the camera pose (and an affine
exposure) over an image pyramid, with a robust point-to-plane residual and a photometric residual.

The model is a set of world-space surfels (:class:`PointModel`: positions, normals, intensities). Each model point
is projected into the frame at the current pose estimate and associated with the frame's vertex at that pixel
(projective association, as KinectFusion / ElasticFusion do; occluded model points land on a nearer surface and
are rejected by the distance gate). Two residuals per associated point:

* **geometric** (point-to-plane, metres): ``r_g = m · (T v − q)`` with ``q``, ``m`` the model point and normal and
  ``v`` the frame's camera-space vertex; pairs farther apart than ``max_dist`` (per level) or whose normals
  disagree (``cos < normal_cos``) are dropped;
* **photometric** (intensity): ``r_p = e^a I(π(T⁻¹ q)) + b − c`` with ``I`` the frame's intensity sampled
  bilinearly, ``c`` the model point's intensity and ``(a, b)`` the frame's affine exposure (solved with the pose),
  weighted by ``photometric`` relative to the geometric term.

Both are scaled by their noise levels (``sigma_geometric``, ``sigma_photometric``) and robustified with Huber
weights (iteratively reweighted least squares); the pose update is a left perturbation ``T ← exp(ξ) T`` of the
camera → world pose, ``ξ = (ρ, φ)`` (translation, rotation) in the world frame. Levels run coarse to fine, each
halving the resolution (depth by :func:`nsplat.data.rgbd.downscale_depth`, intensity by block means; the library's
half-integer pixel centres make the intrinsics scale exactly).
"""
from __future__ import annotations

import dataclasses
import math

import torch
import torch.nn.functional as F
from kornia.geometry.liegroup import Se3

from nsplat.config import require, require_fields
from nsplat.data.fusion import FusionConfig, frame_vertices
from nsplat.data.rgbd import downscale_depth

#: ITU-R BT.601 luma weights: colour → intensity.
LUMA = (0.299, 0.587, 0.114)
#: Fewest pixels on a pyramid level's short side (coarser levels carry too few pixels to register).
MIN_LEVEL_SIZE = 24


@dataclasses.dataclass
class AlignConfig:
    """Registration settings.

    Attributes:
        levels: pyramid levels (each halves the resolution); the coarsest runs first.
        iterations: Gauss-Newton iterations per level, coarse → fine (``levels`` values).
        max_dist: association gate in metres per level, coarse → fine (``levels`` values).
        normal_cos: smallest cosine between associated normals.
        photometric: weight of the photometric term relative to the geometric one (0: geometry only).
        sigma_geometric: point-to-plane noise level (metres).
        sigma_photometric: intensity noise level.
        sigma_depth: growth of the point-to-plane noise with depth: ``σ(z) = sigma_geometric + sigma_depth ·
            (z − 0.4)²`` (metres; a structured-light sensor's axial noise, Nguyen et al. 3DIMPVT 2012: 0.0019).
        huber: Huber threshold in noise-level units.
        model_points: at most this many model points per level's iteration (the finest level; each coarser level
            takes half), drawn evenly from the points in view.
        min_pairs: fewest associated points for an update at the finest level (half per coarser level; fewer:
            the level's pose is kept and the alignment is marked failed).
        prior_trans: std-dev (metres) of a Gaussian prior on the translation away from the start pose (0: none);
            it holds the directions the data leave free (a plane, a blurred photo).
        prior_rot: std-dev (radians) of the prior on the rotation away from the start pose (with ``prior_trans``).
    """

    levels: int = 4
    iterations: list[int] = dataclasses.field(default_factory=lambda: [20, 10, 6, 4])
    max_dist: list[float] = dataclasses.field(default_factory=lambda: [0.2, 0.1, 0.05, 0.03])
    normal_cos: float = 0.7
    photometric: float = 1.0
    sigma_geometric: float = 0.005
    sigma_photometric: float = 0.03
    sigma_depth: float = 0.0019
    huber: float = 2.0
    model_points: int = 12000
    min_pairs: int = 200
    prior_trans: float = 0.02
    prior_rot: float = 0.2

    def __post_init__(self) -> None:
        require_fields(self, levels=">=1", normal_cos="unit", photometric=">=0", sigma_geometric=">0",
                       sigma_photometric=">0", sigma_depth=">=0", huber=">0", model_points=">=100",
                       min_pairs=">=6", prior_trans=">=0", prior_rot=">0")
        require(len(self.iterations) == self.levels and all(i >= 0 for i in self.iterations), "iterations",
                f"{self.levels} counts >= 0 (one per level, coarse to fine)", self.iterations)
        require(len(self.max_dist) == self.levels and all(d > 0 for d in self.max_dist), "max_dist",
                f"{self.levels} distances > 0 (one per level, coarse to fine)", self.max_dist)


@dataclasses.dataclass
class FrameLevel:
    """One pyramid level of a frame: dense camera-space ``vertices [H,W,3]`` and ``normals [H,W,3]``, ``ok [H,W]``
    (a usable vertex), ``intensity [H,W]`` and its gradients ``grad [2,H,W]`` (d/du, d/dv), intrinsics ``K [3,3]``."""

    vertices: torch.Tensor
    normals: torch.Tensor
    ok: torch.Tensor
    intensity: torch.Tensor
    grad: torch.Tensor
    K: torch.Tensor


def intensity(image: torch.Tensor) -> torch.Tensor:
    """``[...,3]`` colours → ``[...]`` intensities."""
    return image @ image.new_tensor(LUMA)


def frame_pyramid(depth: torch.Tensor, image: torch.Tensor, K: torch.Tensor, levels: int,
                  mask: torch.Tensor | None = None) -> list[FrameLevel]:
    """The pyramid of one frame, finest first: ``depth [H,W]`` metres (0 invalid), ``image [H,W,3]``, ``K [3,3]``
    (pixel centres at half-integers), optional ``mask [H,W]`` of usable pixels. At most ``levels`` levels, fewer
    where a coarser one would be under :data:`MIN_LEVEL_SIZE` pixels on its short side."""
    cfg = FusionConfig()
    levels = max(1, min(levels, 1 + int(math.floor(math.log2(min(depth.shape) / MIN_LEVEL_SIZE)))))
    d = depth.float() if mask is None else torch.where(mask, depth.float(), torch.zeros_like(depth.float()))
    gray = intensity(image.float())
    K = K.float()
    out = []
    for lev in range(levels):
        if lev:
            d = downscale_depth(d, 2) if d.shape[0] % 2 == 0 and d.shape[1] % 2 == 0 else d[::2, ::2]
            H2, W2 = d.shape
            gray = F.avg_pool2d(gray[None, None], 2)[0, 0][:H2, :W2]
            K = K.clone()
            K[:2] *= 0.5
        H, W = d.shape
        c = frame_vertices(d, K, cfg)
        verts = torch.zeros(H * W, 3)
        norms = torch.zeros(H * W, 3)
        ok = torch.zeros(H * W, dtype=torch.bool)
        verts[c["index"]] = c["points"].float()
        norms[c["index"]] = c["normals"].float()
        ok[c["index"]] = True
        gx = torch.zeros_like(gray)
        gy = torch.zeros_like(gray)
        gx[:, 1:-1] = 0.5 * (gray[:, 2:] - gray[:, :-2])
        gy[1:-1] = 0.5 * (gray[2:] - gray[:-2])
        out.append(FrameLevel(verts.reshape(H, W, 3), norms.reshape(H, W, 3), ok.reshape(H, W), gray.contiguous(),
                              torch.stack([gx, gy]), K))
    return out


@dataclasses.dataclass
class PointModel:
    """World-space surfels to register against: ``means [N,3]``, unit ``normals [N,3]``, ``intensity [N]``."""

    means: torch.Tensor
    normals: torch.Tensor
    intensity: torch.Tensor


def _sample(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``img [C,H,W]`` at continuous pixel coordinates ``u, v [M]`` (centres at half-integers):
    ``[C,M]``."""
    C, H, W = img.shape
    grid = torch.stack([u / W * 2 - 1, v / H * 2 - 1], -1)[None, None]
    return F.grid_sample(img[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0]


def _in_view(model: PointModel, c2w: torch.Tensor, K: torch.Tensor, H: int, W: int, margin: float
             ) -> torch.Tensor:
    """Indices of the model points in front of the camera and within ``margin`` (fraction of the image) of it."""
    R, t = c2w[:3, :3].float(), c2w[:3, 3].float()
    q = (model.means - t) @ R
    z = q[:, 2]
    zs = z.clamp_min(1e-6)
    u = K[0, 0] * q[:, 0] / zs + K[0, 2]
    v = K[1, 1] * q[:, 1] / zs + K[1, 2]
    keep = (z > 0.05) & (u > -margin * W) & (u < (1 + margin) * W) & (v > -margin * H) & (v < (1 + margin) * H)
    return torch.nonzero(keep)[:, 0]


@dataclasses.dataclass
class AlignResult:
    """A registration's outcome: the camera → world ``c2w [4,4]`` (float64), the exposure ``(a, b)``, the inlier
    count at the finest level, the RMS point-to-plane residual of the inliers (metres), and ``ok`` (enough pairs
    at every level)."""

    c2w: torch.Tensor
    exposure: tuple[float, float]
    inliers: int
    rms: float
    ok: bool


def _system(lvl: FrameLevel, q: torch.Tensor, m: torch.Tensor, c: torch.Tensor, c2w: torch.Tensor,
            exposure: tuple[float, float], max_dist: float, cfg: AlignConfig, need: int
            ) -> tuple[torch.Tensor, torch.Tensor, int, float]:
    """The weighted normal equations ``(H [8,8], g [8])`` of one Gauss-Newton step, the pair count and the RMS
    point-to-plane residual of the pairs."""
    R, t = c2w[:3, :3].float(), c2w[:3, 3].float()
    K = lvl.K
    H_, W_ = lvl.ok.shape
    qc = (q - t) @ R
    z = qc[:, 2]
    zs = z.clamp_min(1e-6)
    u = K[0, 0] * qc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * qc[:, 1] / zs + K[1, 2]
    j, i = torch.floor(u).long(), torch.floor(v).long()
    inside = (z > 0.05) & (j >= 1) & (j < W_ - 1) & (i >= 1) & (i < H_ - 1)
    sel = torch.nonzero(inside)[:, 0]
    j, i = j[sel], i[sel]
    okp = lvl.ok[i, j]
    sel, i, j = sel[okp], i[okp], j[okp]
    vf = lvl.vertices[i, j]
    nf = lvl.normals[i, j]
    p = vf @ R.T + t
    qs, ms = q[sel], m[sel]
    diff = p - qs
    keep = (diff.norm(dim=-1) < max_dist) & ((nf @ R.T) * ms).sum(-1).gt(cfg.normal_cos)
    sel, p, qs, ms, diff = sel[keep], p[keep], qs[keep], ms[keep], diff[keep]
    n = int(sel.numel())
    A = torch.zeros(8, 8, dtype=torch.float64)
    g = torch.zeros(8, dtype=torch.float64)
    if n < need:
        return A, g, n, float("nan")
    # geometric: r = m·(p − q), J = [m, p×m] (left perturbation of c2w), exposure columns 0
    sigma = cfg.sigma_geometric + cfg.sigma_depth * (vf[keep, 2] - 0.4).clamp_min(0) ** 2
    rg = (ms * diff).sum(-1) / sigma
    Jg = torch.cat([ms, torch.cross(p, ms, dim=-1), torch.zeros(n, 2)], 1) / sigma[:, None]
    wg = _huber(rg, cfg.huber)
    A += (Jg.double().T * wg.double()) @ Jg.double()
    g += (Jg.double().T * wg.double()) @ rg.double()
    rms = float((rg * sigma).square().mean().sqrt())
    if cfg.photometric > 0:
        uu, vv, zz, qcs = u[sel], v[sel], zs[sel], qc[sel]
        a, b = exposure
        ea = float(torch.exp(torch.tensor(a)))
        smp = _sample(torch.cat([lvl.intensity[None], lvl.grad]), uu, vv)
        val, gu, gv = smp[0], smp[1], smp[2]
        rp = (ea * val + b - c[sel]) / cfg.sigma_photometric
        # dπ/dqc [n,2,3]; dqc/dξ = Rᵀ[−I, [q]×] (left perturbation of c2w)
        x, y = qcs[:, 0], qcs[:, 1]
        du = torch.stack([K[0, 0] / zz, torch.zeros_like(zz), -K[0, 0] * x / zz ** 2], -1)
        dv = torch.stack([torch.zeros_like(zz), K[1, 1] / zz, -K[1, 1] * y / zz ** 2], -1)
        dI_dqc = ea * (gu[:, None] * du + gv[:, None] * dv)  # [n,3]
        w_ = dI_dqc @ R.T  # the gradient in world axes: [n,3]
        # d r/dρ = −w, d r/dφ = w·([q]× φ) = φ·(w × q)
        Jp = torch.cat([-w_, torch.cross(w_, qs, dim=-1), (ea * val)[:, None], torch.ones(n, 1)], 1)
        Jp = Jp / cfg.sigma_photometric
        wp = _huber(rp, cfg.huber) * cfg.photometric
        A += (Jp.double().T * wp.double()) @ Jp.double()
        g += (Jp.double().T * wp.double()) @ rp.double()
    else:
        A[6, 6] = A[7, 7] = 1.0
    return A, g, n, rms


def _huber(r: torch.Tensor, k: float) -> torch.Tensor:
    """IRLS weights of the Huber loss for residuals ``r`` (in noise units) at threshold ``k``."""
    a = r.abs()
    return torch.where(a <= k, torch.ones_like(a), k / a.clamp_min(1e-12))


@torch.no_grad()
def align(pyramid: list[FrameLevel], model: PointModel, c2w: torch.Tensor, cfg: AlignConfig,
          exposure: tuple[float, float] = (0.0, 0.0)) -> AlignResult:
    """Register a frame (its ``pyramid``, finest first) to ``model``, starting from camera → world ``c2w [4,4]``
    and ``exposure (a, b)``; see the module docstring."""
    T = c2w.double().clone()
    T0inv = torch.linalg.inv(T)
    a, b = exposure
    fine = pyramid[0]
    H, W = fine.ok.shape
    view = _in_view(model, T, fine.K, H, W, 0.25)
    ok, inliers, rms = True, 0, float("nan")
    for lev in reversed(range(min(cfg.levels, len(pyramid)))):
        k = cfg.levels - 1 - lev  # position in the coarse → fine lists
        lvl = pyramid[lev]
        budget = max(100, cfg.model_points // 2 ** lev)
        need = max(6, cfg.min_pairs // 2 ** lev)
        pick = view[torch.linspace(0, view.numel() - 1, min(budget, view.numel())).long()] if view.numel() else view
        q, m, c = model.means[pick], model.normals[pick], model.intensity[pick]
        for _ in range(cfg.iterations[k]):
            A, g, n, r = _system(lvl, q, m, c, T, (a, b), cfg.max_dist[k], cfg, need)
            ok, inliers, rms = n >= need, n, r
            if not ok:
                break
            A = A + 1e-6 * torch.diag(A.diagonal().clamp_min(1e-9)) + 1e-9 * torch.eye(8, dtype=A.dtype)
            if cfg.prior_trans > 0:  # a Gaussian prior on the motion away from the start pose
                xi = Se3.from_matrix((T @ T0inv)[None]).log()[0].double()
                P = torch.cat([torch.full((3,), cfg.prior_trans ** -2), torch.full((3,), cfg.prior_rot ** -2)]).double()
                A[:6, :6] += torch.diag(P)
                g[:6] += P * xi
            delta = -torch.linalg.solve(A, g)
            T = _exp(delta[:6]) @ T
            a, b = a + float(delta[6]), b + float(delta[7])
            if float(delta[:6].abs().max()) < 1e-6:
                break
    return AlignResult(T, (a, b), inliers, rms, ok)


def _exp(xi: torch.Tensor) -> torch.Tensor:
    """``exp`` of a twist ``xi = (ρ, φ) [6]`` (float64) as a 4×4 matrix."""
    return Se3.exp(xi.double()[None]).matrix()[0].detach()
