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

The merge streams (:class:`SurfelMap`): each frame is reduced to per-voxel sums and merged into the map before the
next is looked at, so memory is the map (about 60 bytes a surfel) plus one frame's temporaries whatever the frame
count; the per-frame vertex math is float32, the accumulators float32 (positions relative to their voxel's corner).
``max_points`` caps the map: past it the voxel doubles and the map re-bins (exact for the sums). ``voxel = 0``
starts at the first frame's median pixel footprint and grows by the same doubling. Each surfel's tangent std-dev
is ``scale_factor · max(radius, voxel)``.
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable

import numpy as np
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
        voxel: merge voxel side in metres. The default, 2 cm, is about two pixel footprints at 2 m at 320×240
            (four at 640×480): finer than the refinement's surfels need to start from, coarse enough to average
            several depth readings per voxel. 0 starts at the first frame's median pixel footprint and lets
            ``max_points`` grow it.
        max_points: point cap: past it the voxel doubles (the map re-binned; :class:`SurfelMap`).
        pixel_stride: use every this many pixels along rows and columns.
        edge: relative depth jump to a neighbour that marks a discontinuity (no surfel there).
        grazing: smallest ``|cos|`` between a surfel's normal and its viewing ray.
        scale_factor: tangent std-dev as a multiple of ``max(footprint radius, voxel)``.
        min_frames: drop voxels seen by fewer frames (1 keeps every voxel).
    """

    voxel: float = 0.02
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


def frame_vertices(depth: torch.Tensor, K: torch.Tensor, cfg: FusionConfig,
                   dtype: torch.dtype = torch.float64) -> dict[str, torch.Tensor]:
    """The surfel candidates of one depth map ``[H,W]`` (metres, 0 invalid) with intrinsics ``K [3,3]`` (pixel
    centres at half-integers): camera-space ``points [M,3]``, ``normals [M,3]``, ``radius [M]``, ``weight [M]``
    (all ``dtype``) and the flat pixel ``index [M]`` (row-major in the full map). The fusion computes them in
    float32 (:class:`SurfelMap`); float64, the default, is for the trackers' registration."""
    H, W = depth.shape
    z = depth.to(dtype)
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype) + 0.5, torch.arange(W, dtype=dtype) + 0.5, indexing="ij")
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


#: Voxel coordinates are packed into one int64 key, 21 bits per axis (offset by 2²⁰): ±2²⁰ voxels per axis, ±10 km
#: at 1 cm. The packing is exact (no hash collisions) and invertible (:func:`_decode`), so the map re-bins from its
#: keys alone.
_BITS = 21
_BIAS = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def _encode(q: torch.Tensor) -> torch.Tensor:
    """int64 voxel coordinates ``q [M,3]`` → keys ``[M]`` (their order is x-major, then y, then z)."""
    if q.numel() and (int(q.min()) < -_BIAS or int(q.max()) >= _BIAS):
        raise ValueError(f"fusion: a point lies more than {_BIAS} voxels from the origin (metres? depth_scale?)")
    q = q + _BIAS
    return (q[:, 0] << (2 * _BITS)) | (q[:, 1] << _BITS) | q[:, 2]


def _decode(keys: torch.Tensor) -> torch.Tensor:
    """Keys ``[M]`` → int64 voxel coordinates ``[M,3]`` (the inverse of :func:`_encode`)."""
    return torch.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], 1) - _BIAS


def _unique(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sorted unique keys [V], inverse [M])`` of int64 ``keys [M]``, as ``torch.unique(keys,
    return_inverse=True)``; NumPy's vectorised argsort is an order of magnitude faster than torch's CPU sort here."""
    k = keys.numpy()
    order = np.argsort(k)
    sk = k[order]
    first = np.empty(sk.shape[0], dtype=bool)
    first[:1] = True
    np.not_equal(sk[1:], sk[:-1], out=first[1:])
    inv = np.empty(sk.shape[0], dtype=np.int64)
    inv[order] = np.cumsum(first) - 1
    return torch.from_numpy(sk[first]), torch.from_numpy(inv)


class SurfelMap:
    """A streaming voxel map of surfels: :meth:`add` merges one posed frame at a time, :meth:`surfels` reads the
    fused surfels out at any point. Memory is the map plus one frame's temporaries, whatever the frame count.

    Per occupied voxel of side ``voxel`` (grid origin at the world origin) the map keeps float32 accumulators, one
    row of ``rows [V, 8 + C]``: the confidence sum ``Σw``, ``Σw·(x − corner)`` (positions relative to the voxel's
    corner, so float32 keeps sub-micrometre precision for any room size), ``Σw·n``, ``Σw·colour`` (``C``
    channels) and ``Σw·radius``; ``frames [V]`` (int32) counts the frames that saw the voxel (each frame adds 1 to
    every voxel it touches, once). Rows are ordered by their int64 voxel ``keys [V]`` (sorted, unique): a frame's
    candidates are first reduced to per-voxel partial sums (a sort of their keys), then merged with
    ``torch.searchsorted`` — existing voxels by ``index_add``, new ones inserted in key order (O(V) per frame).

    **The point cap.** Whenever the map holds more than ``cfg.max_points`` voxels the voxel side doubles and the map
    re-bins: each voxel's sums go to the coarser voxel that contains it (a voxel of side 2v holds exactly eight of
    side v, so the sums, and the means read from them, are exactly those of fusing on the coarser grid from the
    start), the corner offsets shifted by ``Σw · (old corner − new corner)``. A coarse voxel's frame count becomes the
    largest of its parts' (a lower bound of the distinct frames; exact again for the frames that follow). On
    surfaces doubling leaves about a quarter of the voxels, so the final count lies between about ``max_points/4``
    and ``max_points`` once the cap was hit. ``cfg.voxel = 0`` starts from the median pixel footprint of the first
    frame with valid depth and grows only by that doubling.
    """

    def __init__(self, cfg: FusionConfig | None = None) -> None:
        self.cfg = cfg or FusionConfig()
        #: The current voxel side (metres); 0 until the first frame when ``cfg.voxel`` is 0.
        self.voxel: float = float(self.cfg.voxel)
        self.keys = torch.zeros(0, dtype=torch.long)
        self.rows = torch.zeros(0, 0)
        self.frames = torch.zeros(0, dtype=torch.int32)
        #: Frames added (with or without valid pixels), candidates merged, re-binnings done.
        self.added = self.candidates = self.doublings = 0
        self.channels: int | None = None

    def __len__(self) -> int:
        return int(self.keys.numel())

    @property
    def nbytes(self) -> int:
        """Bytes held by the map's tensors."""
        return sum(t.numel() * t.element_size() for t in (self.keys, self.rows, self.frames))

    @torch.no_grad()
    def add(self, depth: torch.Tensor, image: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor) -> None:
        """Merge one frame: ``depth [H,W]`` metres (0 invalid), ``image [H,W,C]`` colours of the same pixels,
        ``K [3,3]`` intrinsics (pixel centres at half-integers), ``c2w [4,4]`` camera → world pose."""
        if depth.dim() != 2 or image.dim() != 3 or image.shape[:2] != depth.shape or K.shape != (3, 3) or \
                c2w.shape != (4, 4):
            raise ValueError(f"SurfelMap.add: expected depth [H,W], image [H,W,C], K [3,3], c2w [4,4], got "
                             f"{list(depth.shape)}, {list(image.shape)}, {list(K.shape)}, {list(c2w.shape)}")
        if self.channels is None:
            self.channels = image.shape[-1]
            self.rows = torch.zeros(0, 8 + self.channels)
        elif image.shape[-1] != self.channels:
            raise ValueError(f"SurfelMap.add: {image.shape[-1]} colour channels, the map has {self.channels}")
        self.added += 1
        c = frame_vertices(depth, K, self.cfg, dtype=torch.float32)
        M = c["weight"].numel()
        if M == 0:
            return
        self.candidates += M
        if self.voxel <= 0:
            self.voxel = float(c["radius"].median())
        # world positions in float64 for the keys and corner offsets only (the float32 vertices are exact there)
        R, t = c2w[:3, :3].double(), c2w[:3, 3].double()
        p = torch.addmm(t, c["points"].double(), R.T)
        q = torch.floor(p / self.voxel).long()
        off = (p - q.double() * self.voxel).float()
        w = c["weight"][:, None]
        vals = torch.cat([w, off * w, (c["normals"] @ R.T.float()) * w,
                          image.reshape(-1, self.channels)[c["index"]].float() * w, c["radius"][:, None] * w], 1)
        keys, inv = _unique(_encode(q))
        rows = torch.zeros(keys.numel(), vals.shape[1]).index_add_(0, inv, vals)
        self._merge(keys, rows, torch.ones(keys.numel(), dtype=torch.int32))
        while len(self) > self.cfg.max_points:
            self._double()

    def _merge(self, keys: torch.Tensor, rows: torch.Tensor, frames: torch.Tensor) -> None:
        """Merge sorted unique ``keys [F]`` with their ``rows [F,8+C]`` and ``frames [F]`` into the map (sums add,
        frame counts add)."""
        N = len(self)
        pos = torch.searchsorted(self.keys, keys)
        hit = pos < N
        hit[hit.clone()] = self.keys[pos[hit]] == keys[hit]
        if bool(hit.any()):
            self.rows.index_add_(0, pos[hit], rows[hit])
            self.frames.index_add_(0, pos[hit], frames[hit])
        new = ~hit
        F = int(new.sum())
        if F == 0:
            return
        npos = pos[new]  # where each new key goes among the old ones (sorted, as keys are)
        dest_new = npos + torch.arange(F)
        # each old row moves down by the number of new keys inserted before it
        dest_old = torch.arange(N) + torch.searchsorted(npos, torch.arange(N), right=True)
        out_keys = torch.empty(N + F, dtype=torch.long)
        out_rows = torch.empty(N + F, self.rows.shape[1])
        out_frames = torch.empty(N + F, dtype=torch.int32)
        out_keys[dest_old], out_keys[dest_new] = self.keys, keys[new]
        out_rows[dest_old], out_rows[dest_new] = self.rows, rows[new]
        out_frames[dest_old], out_frames[dest_new] = self.frames, frames[new]
        self.keys, self.rows, self.frames = out_keys, out_rows, out_frames

    def _double(self) -> None:
        """Double the voxel side and re-bin the map's sums into the coarser grid (exact for the sums)."""
        q = _decode(self.keys)
        q2 = torch.div(q, 2, rounding_mode="floor")
        shift = ((q - 2 * q2).double() * self.voxel).float()  # old corner − new corner, in [0, voxel) per axis
        rows = self.rows.clone()
        rows[:, 1:4] += rows[:, :1] * shift
        keys, inv = _unique(_encode(q2))
        self.rows = torch.zeros(keys.numel(), rows.shape[1]).index_add_(0, inv, rows)
        self.frames = torch.zeros(keys.numel(), dtype=torch.int32).scatter_reduce_(0, inv, self.frames, "amax")
        self.keys = keys
        self.voxel *= 2.0
        self.doublings += 1
        log.info("fusion: more than %d surfels, voxel doubled to %.4f m (%d surfels)", self.cfg.max_points,
                 self.voxel, len(self))

    def surfels(self) -> Surfels:
        """The fused surfels so far (voxels seen by at least ``cfg.min_frames`` frames): confidence-weighted means
        of position, normal (renormalised), colour and radius; tangent std-dev ``scale_factor · max(radius,
        voxel)``. Raises ``ValueError`` when no frame had a valid depth pixel."""
        if len(self) == 0:
            raise ValueError("fuse: no valid depth pixel in any frame (check depth_scale and depth_range)")
        keep = self.frames >= self.cfg.min_frames
        rows, C = self.rows[keep], self.channels
        w = rows[:, :1]
        corner = _decode(self.keys[keep]).double() * self.voxel
        means = (corner + (rows[:, 1:4] / w).double()).float()
        normals = torch.nn.functional.normalize(rows[:, 4:7], dim=-1)
        radius = rows[:, 7 + C] / w[:, 0]
        return Surfels(means, normals, rows[:, 7:7 + C] / w, self.cfg.scale_factor * radius.clamp_min(self.voxel),
                       self.frames[keep].clone(), self.voxel)


def fuse(depths: torch.Tensor, images: torch.Tensor, Ks: torch.Tensor, c2w: torch.Tensor,
         cfg: FusionConfig | None = None, progress: bool = True) -> Surfels:
    """Fuse posed depth frames into surfels, one frame at a time (a :class:`SurfelMap`; see the module docstring).

    Args:
        depths: ``[B,H,W]`` metres (0 invalid). images: ``[B,H,W,C]`` colours of the same pixels.
        Ks: ``[B,3,3]`` intrinsics (pixel centres at half-integers). c2w: ``[B,4,4]`` camera → world poses.
        cfg: :class:`FusionConfig` (defaults when ``None``).
        progress: a progress bar over the frames.

    Returns:
        :class:`Surfels`.
    """
    if depths.dim() != 3 or images.shape[:3] != depths.shape or Ks.shape != (depths.shape[0], 3, 3) or \
            c2w.shape != (depths.shape[0], 4, 4):
        raise ValueError(f"fuse: expected depths [B,H,W], images [B,H,W,C], Ks [B,3,3], c2w [B,4,4], got "
                         f"{list(depths.shape)}, {list(images.shape)}, {list(Ks.shape)}, {list(c2w.shape)}")
    return fuse_frames(zip(depths, images, Ks, c2w), cfg, progress, total=depths.shape[0])


def fuse_frames(frames: Iterable[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]],
                cfg: FusionConfig | None = None, progress: bool = True, total: int | None = None) -> Surfels:
    """Fuse a stream of frames ``(depth [H,W], image [H,W,C], K [3,3], c2w [4,4])`` (e.g. a generator decoding
    them from disk one by one): peak memory is the map plus one frame. ``total`` sizes the progress bar."""
    fmap = SurfelMap(cfg)
    for frame in tqdm(frames, desc="fusion", unit="frame", total=total, disable=not progress, leave=False):
        fmap.add(*frame)
    out = fmap.surfels()
    log.info("fusion: %d frames, %d candidates -> %d surfels (voxel %.4f m%s)", fmap.added, fmap.candidates,
             out.means.shape[0], fmap.voxel, f", doubled {fmap.doublings}×" if fmap.doublings else "")
    return out
