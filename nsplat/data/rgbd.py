"""Real RGB-D sequences with a camera trajectory: the TUM RGB-D layout and the pose-file folder layout.

Two layouts are read (docs/data.md, "RGB-D sequences"):

* **TUM RGB-D** (Sturm et al., IROS 2012): ``rgb.txt`` and ``depth.txt`` list ``timestamp filename``; a
  trajectory file lists ``timestamp tx ty tz qx qy qz qw`` (camera → world, Hamilton quaternion, scalar last).
  RGB and depth frames are paired by nearest timestamp within ``max_dt`` seconds, and each pair with the
  trajectory (and the ground truth, when given) the same way, as the benchmark's ``associate.py`` pairs
  them: the candidate pairs closest in time are taken first, each stamp used once.
* **A folder of frames** with one pose file per frame (the 7-Scenes / tsdf-fusion layout):
  ``<frame>.color.png`` (or ``.jpg``), ``<frame>.depth.png`` and ``<frame>.pose.txt`` (a 4×4 camera → world
  matrix), and an intrinsics file (``camera-intrinsics.txt``: the 3×3 matrix) unless the config names the
  intrinsics.

Intrinsics come from the config (``fx fy cx cy`` in OpenCV's pixel convention, centres at integers, with
OpenCV distortion ``k1 k2 p1 p2 k3``) or from one of the three TUM camera presets (:data:`TUM_CAMERAS`). The
photos are undistorted to the pinhole camera with the same ``fx fy cx cy`` (pycolmap's ``FULL_OPENCV`` model,
as :mod:`nsplat.data.undistort` does for captures): colour bilinearly, depth by the nearest sample (never mixing
two surfaces' depths); target pixels whose ray leaves the photo are invalid. ``downscale`` then averages
``d×d`` blocks (depth: the mean of a block whose valid readings agree within 2 %, else invalid). The returned
intrinsics follow the library's convention (pixel centres at half-integers, :mod:`nsplat.cameras`).

Depth PNGs hold ``metres × depth_scale`` (5000 for TUM, 1000 for millimetres); 0, 65535 (a saturated or invalid
reading) and readings outside ``[depth_min, depth_max]`` are invalid. A depth camera that is not registered to the
colour camera (7-Scenes) has its own pinhole intrinsics and a depth → colour transform: its readings are
reprojected into the colour camera's raw photo first (:func:`reproject_depth`). Every check that can fail runs
before any image is decoded, and fails with one line naming the file and what was expected
(:class:`~nsplat.errors.DataError`); the depth scale is checked against the trajectory once the frames are
decoded, before any fusion (:mod:`nsplat.data.depth_checks`).
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch
import torch.nn.functional as F
from tqdm import tqdm

from nsplat.data.tum_format import associate, numbers, read_file_list, read_trajectory, text_rows
from nsplat.data.undistort import source_positions
from nsplat.errors import DataError

#: TUM RGB-D camera presets (the benchmark's documented calibration of each Kinect's RGB camera):
#: ``(fx, fy, cx, cy)`` in OpenCV's pixel convention and distortion ``(k1, k2, p1, p2, k3)``.
TUM_CAMERAS: dict[str, tuple[tuple[float, float, float, float], tuple[float, ...]]] = {
    "fr1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
#: Fewest frames a sequence must pair with its trajectory.
MIN_FRAMES = 3
#: Median valid depth (metres) outside which a depth scale is taken for a wrong one.
PLAUSIBLE_DEPTH = (0.05, 50.0)
#: Valid depth readings of a downscaled block must agree within this relative spread.
BLOCK_AGREE = 0.02
#: The raw depth value of a saturated or invalid reading (16-bit maximum): invalid whatever ``depth_range``.
INVALID_DEPTH = 65535


@dataclasses.dataclass
class RGBDSequence:
    """``B`` RGB-D frames with their trajectory.

    Attributes:
        images: ``[B,H,W,3]`` float32 in [0, 1] (undistorted, downscaled).
        depths: ``[B,H,W]`` float32 metres, 0 where invalid.
        valid: ``[B,H,W]`` bool, pixels inside the undistorted photo.
        Ks: ``[B,3,3]`` float32 pinhole intrinsics (pixel centres at half-integers).
        c2w: ``[B,4,4]`` float64 camera → world poses of the trajectory (OpenCV camera axes).
        c2w_gt: ``[B,4,4]`` float64 ground-truth poses in their own world frame, or ``None``.
        timestamps: ``[B]`` float64 seconds (the RGB frames'; the frame index for the folder layout).
        names: frame names (the RGB file's stem).
    """

    images: torch.Tensor
    depths: torch.Tensor
    valid: torch.Tensor
    Ks: torch.Tensor
    c2w: torch.Tensor
    c2w_gt: torch.Tensor | None
    timestamps: torch.Tensor
    names: list[str]

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    def subset(self, index: Sequence[int]) -> "RGBDSequence":
        """The frames ``index`` in that order."""
        idx = torch.as_tensor(list(index), dtype=torch.long)
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for k, v in out.items():
            if isinstance(v, torch.Tensor):
                out[k] = v[idx]
        out["names"] = [self.names[i] for i in idx.tolist()]
        return RGBDSequence(**out)


@dataclasses.dataclass
class Camera:
    """Pinhole intrinsics ``(fx, fy, cx, cy)`` in OpenCV's convention and distortion ``(k1, k2, p1, p2, k3)``."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def colmap(self, width: int, height: int, distorted: bool = True) -> pycolmap.Camera:
        """The pycolmap camera (COLMAP's pixel centres at half-integers: ``cx + 0.5``)."""
        k1, k2, p1, p2, k3 = self.distortion
        base = [self.fx, self.fy, self.cx + 0.5, self.cy + 0.5]
        if distorted:
            return pycolmap.Camera(model="FULL_OPENCV", width=width, height=height,
                                   params=base + [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0])
        return pycolmap.Camera(model="PINHOLE", width=width, height=height, params=base)

    @property
    def distorted(self) -> bool:
        return any(abs(k) > 0 for k in self.distortion)


def camera_of(preset: str, intrinsics: Sequence[float], distortion: Sequence[float]) -> Camera:
    """The camera from a TUM preset name (``fr1``, ``fr2``, ``fr3``) or from explicit values."""
    if intrinsics:
        if len(intrinsics) != 4 or any(not math.isfinite(v) for v in intrinsics) or min(intrinsics[:2]) <= 0:
            raise DataError(f"intrinsics: expected [fx, fy, cx, cy] with fx, fy > 0, got {list(intrinsics)}")
        dist = tuple(float(v) for v in distortion) if distortion else (0.0,) * 5
        if len(dist) != 5:
            raise DataError(f"distortion: expected [k1, k2, p1, p2, k3], got {list(distortion)}")
        return Camera(*[float(v) for v in intrinsics], distortion=dist)
    if preset not in TUM_CAMERAS:
        raise DataError(f"camera: expected one of {sorted(TUM_CAMERAS)} or explicit intrinsics, got {preset!r}")
    (fx, fy, cx, cy), dist = TUM_CAMERAS[preset]
    return Camera(fx, fy, cx, cy, dist)


# ---------------------------------------------------------------------------------------------- frames
@dataclasses.dataclass
class FrameFiles:
    """What a layout resolves before any image is read: per frame the colour and depth files, the pose
    ``c2w [B,4,4]`` float64, the ground truth (or ``None``), timestamps and the camera."""

    color: list[Path]
    depth: list[Path]
    c2w: torch.Tensor
    c2w_gt: torch.Tensor | None
    timestamps: np.ndarray
    camera: Camera | None


def _existing(paths: list[Path], what: str) -> None:
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise DataError(f"{missing[0]}: missing {what} frame ({len(missing)} of {len(paths)} listed frames are "
                        f"missing)")


def tum_files(root: Path, trajectory: str, groundtruth: str, max_dt: float) -> FrameFiles:
    """Resolve a TUM folder: pair RGB with depth, then with the trajectory (and the ground truth). An empty
    ``trajectory`` keeps every RGB-D pair with identity poses (a trajectory to be estimated from the frames)."""
    if not root.is_dir():
        raise DataError(f"{root}: no such RGB-D sequence folder")
    rgb_t, rgb_f = read_file_list(root / "rgb.txt")
    dep_t, dep_f = read_file_list(root / "depth.txt")
    pairs = associate(rgb_t, dep_t, max_dt)
    if not pairs:
        raise DataError(f"{root}: no RGB and depth frames within {max_dt} s of each other (data.rgbd.max_dt)")
    if trajectory:
        traj_path = _resolve(root, trajectory)
        traj_t, traj = read_trajectory(traj_path)
    else:  # to be estimated from the frames: every RGB-D pair, at the identity for now
        traj_path, traj_t = root / "rgb.txt", rgb_t[[i for i, _ in pairs]]
        traj = torch.eye(4, dtype=torch.float64).expand(len(pairs), 4, 4).clone()
    pose_of = dict(associate(rgb_t[[i for i, _ in pairs]], traj_t, max_dt))
    keep = [k for k in range(len(pairs)) if k in pose_of]
    if len(keep) < MIN_FRAMES:
        raise DataError(f"{traj_path}: the trajectory covers {len(keep)} of {len(pairs)} RGB-D frames within "
                        f"{max_dt} s, need at least {MIN_FRAMES} (data.rgbd.max_dt, or the wrong trajectory?)")
    gt = None
    if groundtruth:
        gt_path = _resolve(root, groundtruth)
        gt_t, gt_all = read_trajectory(gt_path)
        gt_of = dict(associate(rgb_t[[pairs[k][0] for k in keep]], gt_t, max_dt))
        if len(gt_of) < len(keep):
            keep = [keep[k] for k in sorted(gt_of)]
            if len(keep) < MIN_FRAMES:
                raise DataError(f"{gt_path}: the ground truth covers {len(keep)} of the trajectory's frames within "
                                f"{max_dt} s, need at least {MIN_FRAMES}")
            gt_of = dict(associate(rgb_t[[pairs[k][0] for k in keep]], gt_t, max_dt))
        gt = gt_all[[gt_of[k] for k in range(len(keep))]]
    sel = [pairs[k] for k in keep]
    color = [root / rgb_f[i] for i, _ in sel]
    depth = [root / dep_f[j] for _, j in sel]
    _existing(color, "colour")
    _existing(depth, "depth")
    c2w = traj[[pose_of[k] for k in keep]]
    return FrameFiles(color, depth, c2w, gt, rgb_t[[i for i, _ in sel]], None)


def _resolve(root: Path, name: str) -> Path:
    p = Path(name).expanduser()
    return p if p.is_absolute() else root / p


def read_intrinsics_file(path: Path) -> Camera:
    """A 3×3 intrinsics matrix file (``camera-intrinsics.txt``; OpenCV pixel convention)."""
    rows = text_rows(path, 3, "intrinsics")
    if len(rows) != 3:
        raise DataError(f"{path}: expected a 3×3 intrinsics matrix, got {len(rows)} rows")
    K = [numbers(path, r, n) for n, r in rows]
    if K[0][0] <= 0 or K[1][1] <= 0 or K[2] != [0.0, 0.0, 1.0] or abs(K[0][1]) > 1e-9 * K[0][0] or \
            abs(K[1][0]) > 1e-9 * K[1][1]:
        raise DataError(f"{path}: expected [[fx 0 cx] [0 fy cy] [0 0 1]] with fx, fy > 0, got {K}")
    return Camera(K[0][0], K[1][1], K[0][2], K[1][2])


def folder_files(root: Path, intrinsics_file: str) -> FrameFiles:
    """Resolve a pose-file folder: ``*.color.(png|jpg)``, ``*.depth.png``, ``*.pose.txt`` per frame."""
    if not root.is_dir():
        raise DataError(f"{root}: no such RGB-D frame folder")
    colours = sorted([*root.glob("*.color.png"), *root.glob("*.color.jpg")])
    if len(colours) < MIN_FRAMES:
        raise DataError(f"{root}: found {len(colours)} '<frame>.color.png' images, need at least {MIN_FRAMES}")
    stems = [p.name.split(".color.")[0] for p in colours]
    depth = [root / f"{s}.depth.png" for s in stems]
    poses = [root / f"{s}.pose.txt" for s in stems]
    _existing(depth, "depth")
    _existing(poses, "pose")
    mats = []
    for p in poses:
        rows = text_rows(p, 4, "pose")
        if len(rows) != 4:
            raise DataError(f"{p}: expected a 4×4 camera-to-world matrix, got {len(rows)} rows")
        M = torch.tensor([numbers(p, r, n) for n, r in rows], dtype=torch.float64)
        R = M[:3, :3]
        if (M[3] - torch.tensor([0.0, 0, 0, 1], dtype=torch.float64)).abs().max() > 1e-6 or \
                (R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max() > 1e-3 or float(torch.det(R)) <= 0:
            raise DataError(f"{p}: expected a rigid 4×4 camera-to-world matrix (a rotation: orthonormal with "
                            f"determinant +1; last row 0 0 0 1)")
        mats.append(M)
    cam = read_intrinsics_file(_resolve(root, intrinsics_file)) if intrinsics_file else None
    return FrameFiles(colours, depth, torch.stack(mats), None, np.arange(len(colours), dtype=np.float64), cam)


def _read_png(path: Path, depth: bool) -> np.ndarray:
    try:
        img = iio.imread(path)
    except Exception as exc:  # noqa: BLE001 - any decoder failure means an unreadable frame
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0]  # imageio appends a list of plugins
        raise DataError(f"{path}: cannot read the image (truncated or corrupt?): {why}") from None
    if depth:
        if img.ndim != 2 or img.dtype != np.uint16:
            raise DataError(f"{path}: expected a 16-bit single-channel depth image, got shape {img.shape} {img.dtype}")
        return img
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, 2)
    if img.ndim != 3 or img.shape[2] not in (3, 4) or img.dtype != np.uint8:
        raise DataError(f"{path}: expected an 8-bit RGB image, got shape {img.shape} {img.dtype}")
    return img[..., :3]


class _Warp:
    """Undistortion of one camera's photos to its pinhole twin, then block downscaling."""

    def __init__(self, camera: Camera, width: int, height: int) -> None:
        self.identity = not camera.distorted
        if not self.identity:
            pos = source_positions(camera.colmap(width, height), camera.colmap(width, height, distorted=False))
            grid = torch.from_numpy(pos) * torch.tensor([2.0 / width, 2.0 / height], dtype=torch.float64) - 1.0
            self.grid = grid[None].float()
            self.inside = ((pos[..., 0] >= 0) & (pos[..., 0] <= width) & (pos[..., 1] >= 0) & (pos[..., 1] <= height))
        self.size = (height, width)

    def colour(self, img: torch.Tensor) -> torch.Tensor:
        if self.identity:
            return img
        out = F.grid_sample(img.permute(2, 0, 1)[None], self.grid, mode="bilinear", padding_mode="border",
                            align_corners=False)
        return out[0].permute(1, 2, 0)

    def depth(self, d: torch.Tensor) -> torch.Tensor:
        if self.identity:
            return d
        out = F.grid_sample(d[None, None], self.grid, mode="nearest", padding_mode="zeros", align_corners=False)
        return out[0, 0] * torch.from_numpy(self.inside)

    def valid(self) -> torch.Tensor:
        return torch.ones(self.size, dtype=torch.bool) if self.identity else torch.from_numpy(self.inside)


def downscale_depth(depth: torch.Tensor, d: int) -> torch.Tensor:
    """``[H,W]`` → ``[H/d,W/d]``: the mean of each block's readings when all are valid and agree within
    :data:`BLOCK_AGREE`, else 0 (invalid)."""
    if d == 1:
        return depth
    H, W = depth.shape
    blocks = depth[:H // d * d, :W // d * d].reshape(H // d, d, W // d, d).permute(0, 2, 1, 3).reshape(H // d,
                                                                                                      W // d, -1)
    lo, hi = blocks.min(-1).values, blocks.max(-1).values
    ok = (lo > 0) & (hi - lo <= BLOCK_AGREE * lo)
    return torch.where(ok, blocks.mean(-1), torch.zeros_like(lo))


def depth_to_color_matrix(values: Sequence[float]) -> torch.Tensor:
    """The depth → colour camera transform ``[4,4]`` float64 from 12 or 16 row-major numbers (a rigid motion)."""
    if len(values) not in (12, 16) or not all(math.isfinite(v) for v in values):
        raise DataError(f"depth_to_color: expected 12 or 16 finite numbers (a 4×4 row-major matrix), got "
                        f"{list(values)}")
    T = torch.eye(4, dtype=torch.float64)
    T[:len(values) // 4] = torch.tensor(list(values), dtype=torch.float64).reshape(-1, 4)
    R = T[:3, :3]
    if (T[3] - torch.tensor([0.0, 0, 0, 1], dtype=torch.float64)).abs().max() > 1e-6 or \
            (R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max() > 1e-3 or float(torch.det(R)) <= 0:
        raise DataError(f"depth_to_color: expected a rigid transform (a rotation: orthonormal with determinant +1; "
                        f"last row 0 0 0 1), got {list(values)}")
    return T


def reproject_depth(depth: torch.Tensor, depth_camera: Camera, color_camera: Camera,
                    depth_to_color: torch.Tensor | None, width: int, height: int) -> torch.Tensor:
    """A depth camera's map ``depth [h,w]`` (metres, 0 invalid; pinhole ``depth_camera``, OpenCV convention) as
    the colour camera sees it: ``[height,width]`` float32 metres along the colour camera's axis. Each reading is
    moved by ``depth_to_color [4,4]`` (depth → colour camera; ``None``: identity), projected with the colour
    camera's intrinsics and distortion (its raw photo's pixel grid, undistorted afterwards like the photo) to the
    nearest pixel; the nearest reading wins a pixel (a z-buffer), 0 where none lands."""
    v, u = torch.nonzero(depth > 0, as_tuple=True)
    z = depth[v, u].double()
    d = depth_camera
    X = torch.stack([(u - d.cx) / d.fx * z, (v - d.cy) / d.fy * z, z], -1)
    if depth_to_color is not None:
        T = depth_to_color.double()
        X = X @ T[:3, :3].T + T[:3, 3]
    zc = X[:, 2]
    front = zc > 0
    x, y = X[:, 0] / zc.clamp_min(1e-9), X[:, 1] / zc.clamp_min(1e-9)
    k1, k2, p1, p2, k3 = color_camera.distortion
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    uc = torch.round(color_camera.fx * xd + color_camera.cx).long()
    vc = torch.round(color_camera.fy * yd + color_camera.cy).long()
    ok = front & (uc >= 0) & (uc < width) & (vc >= 0) & (vc < height)
    out = torch.full((height * width,), math.inf, dtype=torch.float64)
    out = out.scatter_reduce(0, vc[ok] * width + uc[ok], zc[ok], "amin")
    return torch.where(torch.isfinite(out), out, torch.zeros_like(out)).reshape(height, width).float()


def load_frames(files: FrameFiles, camera: Camera, *, depth_scale: float, depth_range: tuple[float, float],
                downscale: int, progress: bool = True, depth_camera: Camera | None = None,
                depth_to_color: torch.Tensor | None = None) -> RGBDSequence:
    """Decode, undistort and downscale the frames of ``files`` (one progress bar). With ``depth_camera`` (an
    unregistered depth camera's pinhole intrinsics) each depth map is first reprojected into the colour camera
    (:func:`reproject_depth`, ``depth_to_color [4,4]`` the depth → colour transform, identity when ``None``)."""
    first = _read_png(files.color[0], depth=False)
    H, W = first.shape[:2]
    if W % downscale or H % downscale:
        raise DataError(f"downscale: {downscale} does not divide the {W}×{H} frames")
    raw = _read_png(files.depth[0], depth=True)
    raw = raw[(raw > 0) & (raw < INVALID_DEPTH)]
    if raw.size:
        med = float(np.median(raw)) / depth_scale
        if not PLAUSIBLE_DEPTH[0] <= med <= PLAUSIBLE_DEPTH[1]:
            raise DataError(f"depth_scale: {depth_scale} gives a median depth of {med:.3g} m in {files.depth[0].name}, "
                            f"outside the plausible {PLAUSIBLE_DEPTH[0]}-{PLAUSIBLE_DEPTH[1]} m (5000 for TUM, 1000 "
                            f"for millimetres)")
    warp = _Warp(camera, W, H)
    imgs, deps = [], []
    lo, hi = depth_range
    for c, d in tqdm(list(zip(files.color, files.depth)), desc="rgbd frames", unit="frame", disable=not progress,
                     leave=False):
        rgb = _read_png(c, depth=False)
        dep = _read_png(d, depth=True)
        if rgb.shape[:2] != (H, W) or (depth_camera is None and dep.shape != (H, W)):
            raise DataError(f"{c}: frames must all be {W}×{H} (colour and depth), got colour {rgb.shape[1]}×"
                            f"{rgb.shape[0]} and depth {dep.shape[1]}×{dep.shape[0]} ({d.name})")
        z = torch.from_numpy(dep.astype(np.float32)) / depth_scale
        z = torch.where((z >= lo) & (z <= hi) & torch.from_numpy(dep < INVALID_DEPTH), z, torch.zeros_like(z))
        if depth_camera is not None:
            z = reproject_depth(z, depth_camera, camera, depth_to_color, W, H)
        im = warp.colour(torch.from_numpy(rgb).float() / 255.0)
        if downscale > 1:
            im = F.avg_pool2d(im.permute(2, 0, 1)[None], downscale)[0].permute(1, 2, 0)
        imgs.append(im.contiguous())
        deps.append(downscale_depth(warp.depth(z), downscale))
    depths = torch.stack(deps)
    if not bool((depths > 0).any()):
        raise DataError(f"depth_range: no depth reading within [{lo}, {hi}] m at depth_scale {depth_scale} "
                        f"(5000 for TUM, 1000 for millimetres)")
    valid = warp.valid()
    if downscale > 1:
        valid = F.avg_pool2d(valid[None, None].float(), downscale)[0, 0] > 0.999
    s = 1.0 / downscale
    K = torch.tensor([[camera.fx * s, 0.0, (camera.cx + 0.5) * s], [0.0, camera.fy * s, (camera.cy + 0.5) * s],
                      [0.0, 0.0, 1.0]], dtype=torch.float32)
    B = len(files.color)
    return RGBDSequence(torch.stack(imgs), depths, valid.expand(B, *valid.shape).clone(), K.expand(B, 3, 3).clone(),
                        files.c2w, files.c2w_gt, torch.from_numpy(files.timestamps), [p.stem for p in files.color])
