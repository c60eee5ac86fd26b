"""A synthetic room-scale refinement benchmark (the paper's SLAM-refinement application, simulated).

The room is a 4 × 3.5 × 2.6 m box (world z up, floor at z = 0) with textured walls and floor, a table
carrying a checkerboard and a small box, and a chair-like object (seat, back, four legs). A window on
one wall stands for sensor-invalid pixels: the reference shows it saturated white and its pixels (and
a thin calibration border) are marked invalid in the frame masks, like the masked RGB-D pixels in
the paper's data.

Reference frames are rendered by an independent path, the analytic ray tracer of
:mod:`nsplat.data.raytrace` (ray–primitive intersection, procedural albedo, ``s×s`` supersampling),
shaded here with the same 2nd-order SH irradiance model the refinement learns
(:func:`nsplat.render.sh.sh_shade`, ground-truth coefficients :data:`GT_SH`; no shadows, which that model
cannot represent). The cameras follow an arc around the table.

The initial state simulates an RGB-D SLAM result: a lower-density point cloud back-projected from
every ``keyframe_stride``-th frame at every ``pixel_stride``-th pixel, with multiplicative depth
noise, perturbed normals, flying pixels at depth discontinuities and uniform outliers in the room
volume, coloured by the observed (shaded) reference colour; and camera poses perturbed by exactly
``rot_deg`` degrees and ``trans_frac`` × :data:`SCENE_SIZE` (the room's largest extent).

Frames and the cloud are cached under ``cache_dir`` (e.g. the git-ignored ``data_cache/``), keyed
by a hash of the spec.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
from pathlib import Path

import torch

from nsplat.cameras import intrinsics_from_fov, look_at, perturb_viewmats
from nsplat.config import require, require_fields
from nsplat.data.raytrace import Box, Material, Plane, Primitive, albedo, camera_rays, intersect
from nsplat.data.views import PosedViews
from nsplat.render.sh import sh_shade

log = logging.getLogger(__name__)

#: Room extents (x, y, z) in metres; the scene size for pose errors is the largest extent.
ROOM = (4.0, 3.5, 2.6)
SCENE_SIZE = max(ROOM)
#: Index of the window primitive in :func:`room_primitives` (its pixels are invalid).
WINDOW = 0
#: Ground-truth SH radiance coefficients ``[9, 3]`` (basis order of :mod:`nsplat.render.sh`): a warm
#: overhead light, a cool fill from the window side, and some second-order structure.
GT_SH = torch.tensor([
    [2.90, 2.80, 2.60],
    [0.35, 0.30, 0.45],
    [0.55, 0.50, 0.40],
    [-0.30, -0.25, -0.15],
    [0.10, 0.08, 0.05],
    [0.00, 0.02, 0.06],
    [0.15, 0.12, 0.10],
    [-0.08, -0.05, 0.00],
    [0.12, 0.10, 0.08],
], dtype=torch.float64)


@dataclasses.dataclass
class RoomSpec:
    """Settings of the synthetic room benchmark (all of them enter the cache key).

    Attributes:
        width, height: image size in pixels.
        frames: number of frames along the trajectory.
        fov_deg: horizontal field of view.
        supersample: ray-tracer sub-samples per pixel side (anti-aliasing).
        keyframe_stride: every this many frames contributes to the initial cloud.
        pixel_stride: back-project every this many pixels (along rows and columns) of a keyframe.
        depth_noise: relative (multiplicative) Gaussian depth noise std-dev.
        normal_noise_deg: std-dev of the random tilt of initial normals (degrees).
        flying_fraction: fraction of depth-discontinuity samples turned into flying pixels.
        outlier_fraction: uniform outliers in the room volume, as a fraction of the cloud size.
        scale_factor: initial surfel std-dev as a multiple of the back-projected pixel footprint.
        rot_deg: rotation of every perturbed pose (degrees).
        trans_frac: camera-centre offset of every perturbed pose, as a fraction of the scene size.
        seed: seed of the noise and the perturbation.
    """

    width: int = 96
    height: int = 72
    frames: int = 12
    fov_deg: float = 75.0
    supersample: int = 3
    keyframe_stride: int = 3
    pixel_stride: int = 2
    depth_noise: float = 0.01
    normal_noise_deg: float = 8.0
    flying_fraction: float = 0.5
    outlier_fraction: float = 0.02
    scale_factor: float = 0.6
    rot_deg: float = 2.0
    trans_frac: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        require_fields(self, width=">=1", height=">=1", frames=">=1", supersample=">=1", keyframe_stride=">=1",
                       pixel_stride=">=1", depth_noise=">=0", normal_noise_deg=">=0", outlier_fraction=">=0",
                       rot_deg=">=0", trans_frac=">=0", flying_fraction="unit", scale_factor=">0", seed=">=0")
        require(1.0 < self.fov_deg < 170.0, "fov_deg", "a value in (1, 170)", self.fov_deg)

    def key(self) -> str:
        """Short hash of the spec (cache key)."""
        text = json.dumps(dataclasses.asdict(self), sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:12]


@dataclasses.dataclass
class RoomData:
    """The benchmark: reference frames, cameras and the initial (SLAM-like) state.

    Attributes:
        images: ``[B, H, W, 3]`` float32 reference frames.
        masks: ``[B, H, W]`` bool, valid reference pixels.
        viewmats: ``[B, 4, 4]`` float32 ground-truth world→camera matrices.
        viewmats_init: ``[B, 4, 4]`` float32 perturbed (initial) matrices.
        Ks: ``[B, 3, 3]`` float32 intrinsics.
        means, normals: ``[N, 3]`` initial cloud positions and unit normals.
        colours: ``[N, 3]`` observed colours of the cloud points.
        scales: ``[N]`` initial isotropic std-devs.
        outlier: ``[N]`` bool, planted outliers (flying pixels and uniform ones).
        scene_size: the scene size the translation perturbation refers to (metres).
    """

    images: torch.Tensor
    masks: torch.Tensor
    viewmats: torch.Tensor
    viewmats_init: torch.Tensor
    Ks: torch.Tensor
    means: torch.Tensor
    normals: torch.Tensor
    colours: torch.Tensor
    scales: torch.Tensor
    outlier: torch.Tensor
    scene_size: float

    def views(self) -> PosedViews:
        """The reference frames as :class:`PosedViews`: the initial (perturbed) cameras as ``viewmats``,
        the ground truth as ``viewmats_gt``, valid pixels as ``masks``."""
        names = [f"frame_{i:03d}" for i in range(self.images.shape[0])]
        return PosedViews(self.images, self.viewmats_init, self.Ks, names, masks=self.masks,
                          viewmats_gt=self.viewmats)


def room_primitives() -> list[Primitive]:
    """The room's primitives (the window first, see :data:`WINDOW`)."""
    X, Y, Z = ROOM
    wall_a = Material("stripes", (0.80, 0.72, 0.55), (0.55, 0.45, 0.35), 0.35)
    wall_b = Material("rings", (0.55, 0.70, 0.80), (0.30, 0.42, 0.60), 0.45)
    wall_c = Material("checker", (0.85, 0.82, 0.75), (0.60, 0.35, 0.30), 0.5)
    floor = Material("checker", (0.70, 0.62, 0.50), (0.35, 0.28, 0.22), 0.4)
    ceiling = Material("solid", (0.90, 0.90, 0.88))
    wood = Material("stripes", (0.62, 0.42, 0.25), (0.48, 0.30, 0.16), 0.08)
    dark = Material("solid", (0.25, 0.22, 0.20))
    fabric = Material("checker", (0.25, 0.45, 0.30), (0.15, 0.30, 0.20), 0.12)
    board = Material("checker", (0.95, 0.95, 0.95), (0.05, 0.05, 0.05), 0.08)
    poster = Material("rings", (0.90, 0.30, 0.20), (0.95, 0.85, 0.30), 0.12)
    eps, pad = 0.01, 0.05
    prims: list[Primitive] = [
        Plane((eps, 1.5, 1.5), (1.0, 0.0, 0.0), (0.5, 0.45), Material("solid", (1.0, 1.0, 1.0))),  # window
        # walls, floor and ceiling overlap by `pad` so that no ray escapes through a corner (the
        # tangent axes of a plane with normal ±z are (−y, x), see raytrace.Plane)
        Plane((X / 2, Y / 2, 0.0), (0.0, 0.0, 1.0), (Y / 2 + pad, X / 2 + pad), floor),
        Plane((X / 2, Y / 2, Z), (0.0, 0.0, -1.0), (Y / 2 + pad, X / 2 + pad), ceiling),
        Plane((0.0, Y / 2, Z / 2), (1.0, 0.0, 0.0), (Y / 2 + pad, Z / 2 + pad), wall_c),
        Plane((X, Y / 2, Z / 2), (-1.0, 0.0, 0.0), (Y / 2 + pad, Z / 2 + pad), wall_a),
        Plane((X / 2, 0.0, Z / 2), (0.0, 1.0, 0.0), (X / 2 + pad, Z / 2 + pad), wall_b),
        Plane((X / 2, Y, Z / 2), (0.0, -1.0, 0.0), (X / 2 + pad, Z / 2 + pad), wall_a),
        Plane((2.6, Y - eps, 1.4), (0.0, -1.0, 0.0), (0.45, 0.35), poster),
        # table: top and four legs
        Box((2.2, 2.0, 0.74), (0.60, 0.40, 0.03), 0.0, wood),
        *[Box((2.2 + sx * 0.54, 2.0 + sy * 0.34, 0.355), (0.03, 0.03, 0.355), 0.0, dark)
          for sx in (-1, 1) for sy in (-1, 1)],
        # checkerboard lying on the table and a small box
        Plane((2.0, 2.0, 0.775), (0.0, 0.0, 1.0), (0.24, 0.16), board),
        Box((2.55, 2.15, 0.86), (0.10, 0.08, 0.09), 0.5, poster),
        # chair: seat, back, four legs (rotated 0.4 rad about z)
        Box((1.25, 2.55, 0.45), (0.22, 0.22, 0.03), 0.4, fabric),
        Box((1.25 - 0.21 * math.cos(0.4), 2.55 - 0.21 * math.sin(0.4), 0.75), (0.025, 0.22, 0.28), 0.4,
            fabric),
        *[Box((1.25 + 0.18 * (sx * math.cos(0.4) - sy * math.sin(0.4)),
               2.55 + 0.18 * (sx * math.sin(0.4) + sy * math.cos(0.4)), 0.21), (0.025, 0.025, 0.21), 0.4, dark)
          for sx in (-1, 1) for sy in (-1, 1)],
    ]
    return prims


def trajectory(count: int) -> torch.Tensor:
    """``[count, 4, 4]`` float64 cameras on an arc around the table, looking at it from about 1.5 m."""
    a = torch.linspace(-0.5 * math.pi - 0.9, -0.5 * math.pi + 0.9, count, dtype=torch.float64)
    r = 1.45 + 0.15 * torch.sin(3.0 * a)
    eye = torch.stack([2.1 + r * torch.cos(a), 2.0 + r * torch.sin(a) * 0.9 + 0.3,
                       1.45 + 0.1 * torch.cos(2.0 * a)], -1)
    target = torch.stack([2.0 + 0.3 * torch.sin(a), torch.full_like(a, 2.1), torch.full_like(a, 0.7)], -1)
    return look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def render_frame(prims: list[Primitive], viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                 supersample: int) -> dict[str, torch.Tensor]:
    """Ray-trace one frame (float64).

    Returns ``image [H,W,3]`` (SH-shaded albedo, window white, clipped to [0,1]), ``valid [H,W]``
    (no sub-sample on the window), and from the centre ray ``depth [H,W]`` (camera z, inf on a miss),
    ``normal [H,W,3]`` (world, facing the camera) and ``prim [H,W]``.
    """
    s = supersample
    origins, dirs = camera_rays(viewmat, K, width, height, s)
    hit = intersect(origins, dirs, prims)
    rgb = torch.zeros_like(origins)
    for i, prim in enumerate(prims):
        sel = hit.prim == i
        if bool(sel.any()):
            rgb[sel] = albedo(prim.material, hit.local[sel])
    rgb = sh_shade(rgb, hit.normal, GT_SH).clamp(0.0, 1.0)
    window = hit.prim == WINDOW
    rgb[window] = 1.0
    rgb = rgb.reshape(height, width, s * s, 3).mean(2)
    valid = ~window.reshape(height, width, s * s).any(-1)
    # centre ray of each pixel
    o_c, d_c = camera_rays(viewmat, K, width, height, 1)
    hc = intersect(o_c, d_c, prims)
    z_axis = viewmat[2, :3].double()
    depth = hc.t * (d_c @ z_axis)
    return {"image": rgb, "valid": valid, "depth": depth.reshape(height, width),
            "normal": hc.normal.reshape(height, width, 3), "prim": hc.prim.reshape(height, width)}


def _border(height: int, width: int, px: int = 2) -> torch.Tensor:
    m = torch.zeros(height, width, dtype=torch.bool)
    m[px:height - px, px:width - px] = True
    return m


def _tilt(normals: torch.Tensor, deg: float, g: torch.Generator) -> torch.Tensor:
    noise = torch.randn(normals.shape, generator=g, dtype=torch.float64) * math.radians(deg)
    noise = noise - (noise * normals).sum(-1, keepdim=True) * normals
    return torch.nn.functional.normalize(normals + noise, dim=-1)


def initial_cloud(spec: RoomSpec, frames: list[dict[str, torch.Tensor]], viewmats: torch.Tensor,
                  K: torch.Tensor) -> dict[str, torch.Tensor]:
    """The SLAM-like initial cloud from keyframes (see the module docstring); float64 tensors."""
    g = torch.Generator().manual_seed(spec.seed + 1)
    ps = spec.pixel_stride
    means, normals, colours, scales, outl = [], [], [], [], []
    fx = float(K[0, 0])
    for f in range(0, len(frames), spec.keyframe_stride):
        fr, V = frames[f], viewmats[f]
        depth = fr["depth"][::ps, ::ps]
        ok = torch.isfinite(depth) & (fr["prim"][::ps, ::ps] != WINDOW) & fr["valid"][::ps, ::ps]
        rows, cols = torch.nonzero(ok, as_tuple=True)
        z = depth[rows, cols]
        # flying pixels: where the depth jumps to a neighbour, interpolate towards the far side
        d_full = fr["depth"]
        r_full, c_full = rows * ps, cols * ps
        right = d_full[r_full, (c_full + 1).clamp(max=spec.width - 1)]
        down = d_full[(r_full + 1).clamp(max=spec.height - 1), c_full]
        neigh = torch.maximum(torch.where(torch.isfinite(right), right, z), torch.where(torch.isfinite(down), down, z))
        edge = (neigh - z) > 0.08 * z
        fly = edge & (torch.rand(z.shape, generator=g, dtype=torch.float64) < spec.flying_fraction)
        mix = torch.rand(z.shape, generator=g, dtype=torch.float64) * 0.6 + 0.2
        z = torch.where(fly, z + mix * (neigh - z), z)
        z = z * (1.0 + spec.depth_noise * torch.randn(z.shape, generator=g, dtype=torch.float64))
        u, v = c_full.double() + 0.5, r_full.double() + 0.5
        cam = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
        R, t = V[:3, :3].double(), V[:3, 3].double()
        world = (cam - t) @ R  # Rᵀ (x − t) for row vectors
        means.append(world)
        normals.append(_tilt(fr["normal"][r_full, c_full], spec.normal_noise_deg, g))
        colours.append(fr["image"][r_full, c_full])
        scales.append(spec.scale_factor * ps * z / fx)
        outl.append(fly)
    means_t, normals_t = torch.cat(means), torch.cat(normals)
    colours_t, scales_t, outl_t = torch.cat(colours), torch.cat(scales), torch.cat(outl)
    n_out = int(round(spec.outlier_fraction * means_t.shape[0]))
    if n_out:
        lo = torch.tensor([0.2, 0.2, 0.1], dtype=torch.float64)
        hi = torch.tensor(ROOM, dtype=torch.float64) - 0.2
        pts = lo + (hi - lo) * torch.rand(n_out, 3, generator=g, dtype=torch.float64)
        nrm = torch.nn.functional.normalize(torch.randn(n_out, 3, generator=g, dtype=torch.float64), dim=-1)
        col = torch.rand(n_out, 3, generator=g, dtype=torch.float64)
        means_t = torch.cat([means_t, pts])
        normals_t = torch.cat([normals_t, nrm])
        colours_t = torch.cat([colours_t, col])
        scales_t = torch.cat([scales_t, torch.full((n_out,), float(scales_t.median()), dtype=torch.float64)])
        outl_t = torch.cat([outl_t, torch.ones(n_out, dtype=torch.bool)])
    return {"means": means_t, "normals": normals_t, "colours": colours_t, "scales": scales_t, "outlier": outl_t}


def generate(spec: RoomSpec) -> RoomData:
    """Render the frames and build the initial state (no caching; see :func:`load_room`)."""
    prims = room_primitives()
    V = trajectory(spec.frames)
    K = intrinsics_from_fov(math.radians(spec.fov_deg), spec.width, spec.height, dtype=torch.float64)[0]
    frames = [render_frame(prims, V[i], K, spec.width, spec.height, spec.supersample) for i in range(spec.frames)]
    border = _border(spec.height, spec.width)
    cloud = initial_cloud(spec, frames, V, K)
    g = torch.Generator().manual_seed(spec.seed + 2)
    V_init = perturb_viewmats(V, spec.rot_deg, spec.trans_frac * SCENE_SIZE, generator=g)
    f32 = torch.float32
    return RoomData(
        images=torch.stack([f["image"] for f in frames]).to(f32),
        masks=torch.stack([f["valid"] & border for f in frames]),
        viewmats=V.to(f32), viewmats_init=V_init.to(f32),
        Ks=K.expand(spec.frames, 3, 3).to(f32).clone(),
        means=cloud["means"].to(f32), normals=cloud["normals"].to(f32), colours=cloud["colours"].to(f32),
        scales=cloud["scales"].to(f32), outlier=cloud["outlier"], scene_size=SCENE_SIZE,
    )


def load_room(spec: RoomSpec, cache_dir: str | Path | None = None) -> RoomData:
    """The benchmark for ``spec``, read from ``cache_dir/room-<key>.pt`` or generated and cached."""
    if cache_dir is None:
        return generate(spec)
    path = Path(cache_dir) / f"room-{spec.key()}.pt"
    if path.is_file():
        return RoomData(**torch.load(path, weights_only=False))
    data = generate(spec)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(dataclasses.asdict(data), tmp)
    tmp.replace(path)
    log.info("room benchmark cached at %s (%d frames, %d points)", path, spec.frames, data.means.shape[0])
    return data
