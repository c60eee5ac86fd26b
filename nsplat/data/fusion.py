"""Point-based fusion of posed depth frames into surfels (the initial scene of an RGB-D refinement).

In the spirit of point-based SLAM's fusion (Keller et al., 3DV 2013), without its projective data association:

1. every valid depth pixel of a frame is back-projected through its pixel centre to a camera-space vertex; its
   normal is the cross product of the vertex map's central differences (oriented towards the camera), left out
   at depth discontinuities (a neighbour's depth differs by more than ``edge`` of its own) and at grazing angles
   (``|cos|`` between the normal and the viewing ray below ``grazing``);
2. its radius is the sample's footprint on the surface, ``s · z / (f · |cos|)`` (``f`` the mean focal length in
   pixels, ``s`` the ``pixel_stride``: a sample stands for ``s × s`` pixels); its confidence is Keller et al.'s
   radial weight ``exp(−γ² / (2 · 0.6²))`` (``γ`` the distance to the image centre over the half-diagonal), times
   ``|cos|``;
3. the vertices go to the world along the trajectory and merge per voxel of side ``voxel``: position, normal,
   colour and radius become confidence-weighted means over every frame that saw the voxel.

``voxel = 0`` starts at the median pixel footprint and grows it until at most ``max_points`` surfels remain (a
point budget). Each surfel's tangent std-dev is ``scale_factor · max(radius, voxel)``.
"""
from __future__ import annotations

import dataclasses
import logging
import math

import torch
from tqdm import tqdm

from nsplat.config import require_fields

log = logging.getLogger(__name__)

#: Keller et al.'s radial confidence width (fraction of the half-diagonal).
RADIAL_SIGMA = 0.6


@dataclasses.dataclass
class FusionConfig:
    """Depth fusion settings.

    Attributes:
        voxel: merge voxel side in metres; 0 chooses it from ``max_points``.
        max_points: point budget when ``voxel`` is 0.
        pixel_stride: use every this many pixels along rows and columns.
        edge: relative depth jump to a neighbour that marks a discontinuity (no surfel there).
        grazing: smallest ``|cos|`` between a surfel's normal and its viewing ray.
        scale_factor: tangent std-dev as a multiple of ``max(footprint radius, voxel)``.
        min_frames: drop voxels seen by fewer frames (1 keeps every voxel).
    """

    voxel: float = 0.0
    max_points: int = 150_000
    pixel_stride: int = 1
    edge: float = 0.03
    grazing: float = 0.2
    scale_factor: float = 0.6
    min_frames: int = 1

    def __post_init__(self) -> None:
        require_fields(self, voxel=">=0", max_points=">=1", pixel_stride=">=1", edge=">0", grazing="unit",
                       scale_factor=">0", min_frames=">=1")


@dataclasses.dataclass
class Surfels:
    """Fused surfels: ``means [N,3]``, unit ``normals [N,3]``, ``colours [N,3]``, tangent ``scales [N]`` (std-devs)
    and per-surfel ``frames [N]`` (how many frames saw it), all float32; ``voxel`` the merge voxel side used."""

    means: torch.Tensor
    normals: torch.Tensor
    colours: torch.Tensor
    scales: torch.Tensor
    frames: torch.Tensor
    voxel: float


def frame_vertices(depth: torch.Tensor, K: torch.Tensor, cfg: FusionConfig) -> dict[str, torch.Tensor]:
    """The surfel candidates of one depth map ``[H,W]`` (metres, 0 invalid) with intrinsics ``K [3,3]`` (pixel
    centres at half-integers): camera-space ``points [M,3]``, ``normals [M,3]``, ``radius [M]``, ``weight [M]``
    and the flat pixel ``index [M]`` (row-major in the full map)."""
    H, W = depth.shape
    z = depth.double()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                          indexing="ij")
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    X = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)
    ok = z > 0
    inner = torch.zeros_like(ok)
    inner[1:-1, 1:-1] = True
    zc = z[1:-1, 1:-1]
    for dz in (z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]):
        inner[1:-1, 1:-1] &= (dz > 0) & ((dz - zc).abs() <= cfg.edge * zc)
    ok &= inner
    dx = torch.zeros_like(X)
    dy = torch.zeros_like(X)
    dx[:, 1:-1] = X[:, 2:] - X[:, :-2]
    dy[1:-1] = X[2:] - X[:-2]
    n = torch.nn.functional.normalize(torch.cross(dx, dy, dim=-1), dim=-1)
    ray = torch.nn.functional.normalize(X, dim=-1)
    cos = (n * ray).sum(-1)
    n = torch.where(cos[..., None] > 0, -n, n)  # towards the camera
    cos = cos.abs()
    ok &= cos >= cfg.grazing
    if cfg.pixel_stride > 1:
        stride = torch.zeros_like(ok)
        stride[::cfg.pixel_stride, ::cfg.pixel_stride] = True
        ok &= stride
    f = 0.5 * (fx + fy)
    gamma = torch.sqrt(((u - 0.5 * W) ** 2 + (v - 0.5 * H) ** 2) / (0.25 * (W * W + H * H)))
    weight = torch.exp(-gamma ** 2 / (2 * RADIAL_SIGMA ** 2)) * cos
    idx = torch.nonzero(ok.reshape(-1))[:, 0]
    return {"points": X.reshape(-1, 3)[idx], "normals": n.reshape(-1, 3)[idx],
            "radius": (cfg.pixel_stride * z / (f * cos.clamp_min(cfg.grazing))).reshape(-1)[idx],
            "weight": weight.reshape(-1)[idx], "index": idx}


def _candidates(depths: torch.Tensor, images: torch.Tensor, Ks: torch.Tensor, c2w: torch.Tensor, cfg: FusionConfig,
                progress: bool) -> dict[str, torch.Tensor]:
    """World-space candidates of every frame, concatenated (float64), with ``frame [M]`` indices."""
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in ("points", "normals", "colours", "radius", "weight",
                                                             "frame")}
    for b in tqdm(range(depths.shape[0]), desc="fusion", unit="frame", disable=not progress, leave=False):
        c = frame_vertices(depths[b], Ks[b], cfg)
        R, t = c2w[b, :3, :3].double(), c2w[b, :3, 3].double()
        parts["points"].append(c["points"] @ R.T + t)
        parts["normals"].append(c["normals"] @ R.T)
        parts["colours"].append(images[b].reshape(-1, images.shape[-1])[c["index"]].double())
        parts["radius"].append(c["radius"])
        parts["weight"].append(c["weight"])
        parts["frame"].append(torch.full_like(c["radius"], b, dtype=torch.long))
    return {k: torch.cat(v) for k, v in parts.items()}


def _voxel_keys(points: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(unique voxel ids [V], inverse [M])`` of points ``[M,3]`` on a grid of side ``voxel``."""
    q = torch.floor((points - points.min(0).values) / voxel).long()
    dims = q.max(0).values + 1
    key = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    return torch.unique(key, return_inverse=True)


def fuse(depths: torch.Tensor, images: torch.Tensor, Ks: torch.Tensor, c2w: torch.Tensor,
         cfg: FusionConfig | None = None, progress: bool = True) -> Surfels:
    """Fuse posed depth frames into surfels (see the module docstring).

    Args:
        depths: ``[B,H,W]`` metres (0 invalid). images: ``[B,H,W,C]`` colours of the same pixels.
        Ks: ``[B,3,3]`` intrinsics (pixel centres at half-integers). c2w: ``[B,4,4]`` camera → world poses.
        cfg: :class:`FusionConfig` (defaults when ``None``).

    Returns:
        :class:`Surfels`.
    """
    cfg = cfg or FusionConfig()
    if depths.dim() != 3 or images.shape[:3] != depths.shape or Ks.shape != (depths.shape[0], 3, 3) or \
            c2w.shape != (depths.shape[0], 4, 4):
        raise ValueError(f"fuse: expected depths [B,H,W], images [B,H,W,C], Ks [B,3,3], c2w [B,4,4], got "
                         f"{list(depths.shape)}, {list(images.shape)}, {list(Ks.shape)}, {list(c2w.shape)}")
    c = _candidates(depths, images, Ks, c2w, cfg, progress)
    if c["points"].shape[0] == 0:
        raise ValueError("fuse: no valid depth pixel in any frame (check depth_scale and depth_range)")
    voxel = cfg.voxel
    if voxel <= 0:
        voxel = float(c["radius"].median())
        while True:
            count = _voxel_keys(c["points"], voxel)[0].numel()
            if count <= cfg.max_points:
                break
            voxel *= max(1.02, math.sqrt(count / cfg.max_points))
    _, inv = _voxel_keys(c["points"], voxel)
    V = int(inv.max()) + 1
    w = c["weight"]
    wsum = torch.zeros(V, dtype=torch.float64).index_add_(0, inv, w)

    def mean(x: torch.Tensor) -> torch.Tensor:
        acc = torch.zeros(V, *x.shape[1:], dtype=torch.float64).index_add_(0, inv, x * w.reshape(-1, *[1] *
                                                                                                 (x.dim() - 1)))
        return acc / wsum.reshape(-1, *[1] * (x.dim() - 1))

    seen = torch.zeros(V, c["frame"].max() + 1, dtype=torch.bool)
    seen[inv, c["frame"]] = True
    frames = seen.sum(1)
    keep = frames >= cfg.min_frames
    normals = torch.nn.functional.normalize(mean(c["normals"]), dim=-1)
    radius = mean(c["radius"])
    out = Surfels(mean(c["points"])[keep].float(), normals[keep].float(), mean(c["colours"])[keep].float(),
                  (cfg.scale_factor * radius.clamp_min(voxel))[keep].float(), frames[keep].int(), voxel)
    log.info("fusion: %d frames, %d candidates -> %d surfels (voxel %.4f m)", depths.shape[0], inv.numel(),
             out.means.shape[0], voxel)
    return out
