"""RGB-D camera tracking frame to model, and the global re-alignment of a trajectory to its own fused model.

* :func:`track` estimates a trajectory from the frames alone (or re-tracks a given one): each frame is registered
  (:func:`nsplat.data.registration.align`) to the surfels fused so far from the keyframes (:class:`ModelMap`),
  starting from a prediction: the constant-velocity motion, or the given trajectory's relative motion when one
  is given (so a drifting SLAM result re-tracks with its own local motion as the prior and the model as the
  reference). A frame becomes a keyframe and enters the model when it has moved ``keyframe_trans`` metres or
  ``keyframe_rot_deg`` degrees from the last keyframe.
* :func:`realign` runs ``rounds`` of: fuse the keyframes along the current poses, register every frame to that
  model from its current pose, keep the first frame's pose (the gauge).

The model merges points per voxel of side ``voxel`` (confidence-weighted means of position, normal and
exposure-compensated intensity); it doubles its voxel when it holds more than ``max_points``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from typing import Iterator, Literal

import torch
from tqdm import tqdm

from nsplat.config import require, require_fields
from nsplat.data.fusion import FusionConfig, frame_vertices
from nsplat.data.registration import AlignConfig, PointModel, align, frame_pyramid, intensity

log = logging.getLogger(__name__)


@dataclasses.dataclass
class TrackingConfig:
    """Tracker settings.

    Attributes:
        align: :class:`nsplat.data.registration.AlignConfig`.
        keyframe_trans: translation (metres) from the last keyframe that makes a keyframe.
        keyframe_rot_deg: rotation (degrees) from the last keyframe that makes a keyframe.
        voxel: the model's merge voxel (metres).
        stride: pixel stride of a keyframe's points entering the model.
        max_points: the model's point cap (its voxel doubles past it).
        rounds: global re-alignment rounds after tracking (:func:`realign`).
        threads: torch threads while tracking (restored after; 0: leave as set). The registration's tensors are
            small (thousands of points): one thread is as fast, and more oversubscribe a busy machine (measured 40×
            slower with 2 threads while another job shared the 2 cores).
        predict: each frame's start without a given trajectory: ``velocity`` (the last motion repeated) or
            ``last`` (the last pose).
    """

    align: AlignConfig = dataclasses.field(default_factory=AlignConfig)
    keyframe_trans: float = 0.05
    keyframe_rot_deg: float = 5.0
    voxel: float = 0.01
    stride: int = 2
    max_points: int = 400_000
    rounds: int = 2
    threads: int = 1
    predict: Literal["velocity", "last"] = "velocity"

    def __post_init__(self) -> None:
        require_fields(self, keyframe_trans=">=0", keyframe_rot_deg=">=0", voxel=">0", stride=">=1",
                       max_points=">=1000", rounds=">=0", threads=">=0")
        require(self.predict in ("velocity", "last"), "predict", "'velocity' or 'last'", self.predict)


class ModelMap:
    """A voxel-merged surfel model in world space: per voxel the weight and the weighted sums of position, normal
    and intensity (float64 sums, so merging is exact whatever the order)."""

    def __init__(self, voxel: float, max_points: int) -> None:
        self.voxel, self.max_points = voxel, max_points
        self.keys = torch.zeros(0, dtype=torch.long)
        self.sums = torch.zeros(0, 8, dtype=torch.float64)  # weight, position·w (3), normal·w (3), intensity·w

    def _key(self, points: torch.Tensor) -> torch.Tensor:
        q = torch.floor(points / self.voxel).long() + (1 << 20)
        return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]

    def add(self, points: torch.Tensor, normals: torch.Tensor, values: torch.Tensor, weight: torch.Tensor) -> None:
        """Merge world ``points [M,3]``, ``normals [M,3]``, intensities ``values [M]`` with weights ``weight [M]``."""
        w = weight.double()[:, None]
        rows = torch.cat([w, points.double() * w, normals.double() * w, values.double()[:, None] * w], 1)
        self._merge(torch.cat([self.keys, self._key(points.double())]), torch.cat([self.sums, rows]))
        while self.keys.numel() > self.max_points:
            self.voxel *= 2.0
            log.info("tracking model: %d points, voxel doubled to %.4f m", self.keys.numel(), self.voxel)
            self._merge(self._key(self.sums[:, 1:4] / self.sums[:, :1]), self.sums)

    def _merge(self, keys: torch.Tensor, rows: torch.Tensor) -> None:
        self.keys, inv = torch.unique(keys, return_inverse=True)
        self.sums = torch.zeros(self.keys.numel(), rows.shape[1], dtype=torch.float64).index_add_(0, inv, rows)

    def model(self) -> PointModel:
        """The model's surfels (float32)."""
        w = self.sums[:, :1]
        return PointModel((self.sums[:, 1:4] / w).float(),
                          torch.nn.functional.normalize(self.sums[:, 4:7], dim=-1).float(),
                          (self.sums[:, 7] / w[:, 0]).float())

    def __len__(self) -> int:
        return int(self.keys.numel())


def _add_frame(model: ModelMap, depth: torch.Tensor, image: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor,
               exposure: tuple[float, float], stride: int) -> None:
    c = frame_vertices(depth, K, FusionConfig(pixel_stride=stride))
    R, t = c2w[:3, :3].double(), c2w[:3, 3].double()
    a, b = exposure
    gray = intensity(image.float()).reshape(-1)[c["index"]].double() * math.exp(a) + b
    model.add(c["points"] @ R.T + t, c["normals"] @ R.T, gray, c["weight"])


def _moved(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """Translation (metres) and rotation (degrees) between poses ``a, b [4,4]``."""
    E = torch.linalg.inv(a) @ b
    cos = float(((E[:3, :3].trace() - 1) / 2).clamp(-1, 1))
    return float(E[:3, 3].norm()), math.degrees(math.acos(cos))


@dataclasses.dataclass
class Trajectory:
    """A tracker's output: camera → world ``c2w [B,4,4]`` (float64, the first frame's pose as given or the
    identity), the ``keyframes`` (indices), each frame's inlier count ``inliers [B]`` and RMS point-to-plane
    residual ``rms [B]`` (metres), and the frames whose registration failed (``lost``: kept at the prediction)."""

    c2w: torch.Tensor
    keyframes: list[int]
    inliers: torch.Tensor
    rms: torch.Tensor
    lost: list[int]


@torch.no_grad()
def track(depths: torch.Tensor, images: torch.Tensor, Ks: torch.Tensor, cfg: TrackingConfig | None = None,
          init: torch.Tensor | None = None, progress: bool = True, masks: torch.Tensor | None = None
          ) -> Trajectory:
    """Track the frames in order (see the module docstring), then :func:`realign` ``cfg.rounds`` times.

    Args:
        depths: ``[B,H,W]`` metres (0 invalid). images: ``[B,H,W,3]`` in [0, 1]. Ks: ``[B,3,3]`` (pixel centres
            at half-integers).
        init: ``[B,4,4]`` camera → world poses whose relative motions predict each frame (and whose first pose is
            the output's first); ``None``: constant velocity from the identity.
        masks: ``[B,H,W]`` usable pixels (default: all).
    """
    cfg = cfg or TrackingConfig()
    with _threads(cfg.threads):
        return _track(depths, images, Ks, cfg, init, progress, masks)


@contextlib.contextmanager
def _threads(n: int) -> Iterator[None]:
    """Within the block torch uses ``n`` threads (0: unchanged)."""
    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _track(depths: torch.Tensor, images: torch.Tensor, Ks: torch.Tensor, cfg: TrackingConfig,
           init: torch.Tensor | None, progress: bool, masks: torch.Tensor | None) -> Trajectory:
    B = depths.shape[0]
    a_cfg = cfg.align
    c2w = torch.zeros(B, 4, 4, dtype=torch.float64)
    c2w[0] = torch.eye(4, dtype=torch.float64) if init is None else init[0].double()
    model = ModelMap(cfg.voxel, cfg.max_points)
    exposure: list[tuple[float, float]] = [(0.0, 0.0)] * B
    inliers = torch.zeros(B, dtype=torch.long)
    rms = torch.full((B,), float("nan"), dtype=torch.float64)
    _add_frame(model, _masked(depths, masks, 0), images[0], Ks[0], c2w[0], exposure[0], cfg.stride)
    keyframes, lost, last_key = [0], [], 0
    for k in tqdm(range(1, B), desc="tracking", unit="frame", disable=not progress, leave=False):
        if init is not None:
            pred = c2w[k - 1] @ torch.linalg.inv(init[k - 1].double()) @ init[k].double()
        elif k >= 2 and cfg.predict == "velocity":
            pred = c2w[k - 1] @ torch.linalg.inv(c2w[k - 2]) @ c2w[k - 1]
        else:
            pred = c2w[k - 1].clone()
        pyr = frame_pyramid(depths[k], images[k], Ks[k], a_cfg.levels, None if masks is None else masks[k])
        pm = model.model()
        res = align(pyr, pm, pred, a_cfg, exposure[k - 1])
        if not res.ok:  # from the last pose instead of the prediction
            res = align(pyr, pm, c2w[k - 1], a_cfg, exposure[k - 1])
        if not res.ok:
            lost.append(k)
            log.warning("tracking: frame %d lost (%d pairs at the finest level): kept at the last pose", k,
                        res.inliers)
            res = dataclasses.replace(res, c2w=c2w[k - 1].clone(), exposure=exposure[k - 1])
        c2w[k], exposure[k], inliers[k], rms[k] = res.c2w, res.exposure, res.inliers, res.rms
        dt, dr = _moved(c2w[last_key], c2w[k])
        if res.ok and (dt >= cfg.keyframe_trans or dr >= cfg.keyframe_rot_deg):
            _add_frame(model, _masked(depths, masks, k), images[k], Ks[k], c2w[k], exposure[k], cfg.stride)
            keyframes.append(k)
            last_key = k
    out = Trajectory(c2w, keyframes, inliers, rms, lost)
    for r in range(cfg.rounds):
        out = realign(depths, images, Ks, out, cfg, progress, masks, f"re-alignment {r + 1}/{cfg.rounds}")
    return out


def _masked(depths: torch.Tensor, masks: torch.Tensor | None, k: int) -> torch.Tensor:
    return depths[k] if masks is None else torch.where(masks[k], depths[k], torch.zeros_like(depths[k]))


@torch.no_grad()
def realign(depths: torch.Tensor, images: torch.Tensor, Ks: torch.Tensor, traj: Trajectory, cfg: TrackingConfig,
            progress: bool = True, masks: torch.Tensor | None = None, desc: str = "re-alignment") -> Trajectory:
    """One round of global re-alignment: fuse the keyframes along ``traj`` into a model, register every frame to
    it from its pose in ``traj``, and move the whole result so that the first frame keeps its pose."""
    B = depths.shape[0]
    model = ModelMap(cfg.voxel, cfg.max_points)
    for k in traj.keyframes:
        _add_frame(model, _masked(depths, masks, k), images[k], Ks[k], traj.c2w[k], (0.0, 0.0), cfg.stride)
    pm = model.model()
    c2w = traj.c2w.clone()
    inliers = traj.inliers.clone()
    rms = traj.rms.clone()
    lost = []
    for k in tqdm(range(B), desc=desc, unit="frame", disable=not progress, leave=False):
        pyr = frame_pyramid(depths[k], images[k], Ks[k], cfg.align.levels, None if masks is None else masks[k])
        res = align(pyr, pm, traj.c2w[k], cfg.align)
        if res.ok:
            c2w[k], inliers[k], rms[k] = res.c2w, res.inliers, res.rms
        else:
            lost.append(k)
    c2w = traj.c2w[0] @ torch.linalg.inv(c2w[0]) @ c2w
    return Trajectory(c2w, traj.keyframes, inliers, rms, lost)
