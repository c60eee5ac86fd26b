"""The refine task's data: the frames to refine against and the initial scene (``data.source``: ``room``,
``nerf`` or ``rgbd``).

For ``rgbd`` the sequence is split into training frames (refined with the scene) and held-out frames (every
``holdout_every``-th, scored after their cameras are fitted to the frozen scene); the initial cloud is fused
from the training frames' depth along the given trajectory (or read from the SLAM system's PLY).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nsplat.cameras import perturb_viewmats
from nsplat.config import ConfigError
from nsplat.data.depth_checks import check_depth_scale, same_trajectory
from nsplat.data.fusion import fuse
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.paths import resolve, resolve_data
from nsplat.data.pointclouds import read_point_ply, read_vertex_element
from nsplat.data.rgbd import RGBDSequence, camera_of, depth_to_color_matrix, folder_files, load_frames, tum_files
from nsplat.data.tracking import TrackingConfig, track
from nsplat.data.views import PosedViews
from nsplat.errors import DataError
from nsplat.scene import SurfelScene
from nsplat.tasks.refine.config import Config, RGBDSource
from nsplat.tasks.refine.room import load_room

log = logging.getLogger("nsplat.tasks.refine")

#: The default RGB-D sequence under the data root (``nsplat data fetch tum_fr1_rpy`` has the whole sequence).
DEFAULT_RGBD = "rgbd/tum_fr1_rpy_50"


@dataclasses.dataclass
class Sequence:
    """The timeline of an RGB-D source: every frame's timestamp ``[F]`` (float64), the initial camera → world poses
    ``c2w [F,4,4]`` (float64), the ground truth ``c2w_gt [F,4,4]`` or ``None``, which frames train
    (``train``) and which are held out (``heldout``), as indices into the timeline, and where the initial
    trajectory came from (``source``: ``{"trajectory": file name or "estimate", ...the tracker's figures}``)."""

    timestamps: torch.Tensor
    c2w: torch.Tensor
    c2w_gt: torch.Tensor | None
    train: list[int]
    heldout: list[int]
    source: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class RefineData:
    """What :func:`load_data` returns: training ``frames``, the initial ``scene``, and for an RGB-D source the
    ``heldout`` frames and the ``sequence`` (else ``None``); with ``data.rgbd.retrack`` the refinement starts
    from the re-tracked trajectory and ``initial`` holds the same along the trajectory as given (what "before"
    scores)."""

    frames: PosedViews
    scene: SurfelScene
    heldout: PosedViews | None = None
    sequence: Sequence | None = None
    initial: "RefineData | None" = None


def split(count: int, every: int) -> tuple[list[int], list[int]]:
    """``(train, heldout)`` frame indices: every ``every``-th frame from the first is held out (0: none)."""
    held = list(range(0, count, every)) if every else []
    return [i for i in range(count) if i not in set(held)], held


def _views(seq: RGBDSequence, valid: str) -> PosedViews:
    """The frames as posed views; ``viewmats_gt`` is the ground truth in its own world frame (compare after an
    alignment only)."""
    mask = seq.valid & (seq.depths > 0) if valid == "depth" else seq.valid.clone()
    gt = None if seq.c2w_gt is None else torch.linalg.inv(seq.c2w_gt).float()
    return PosedViews(seq.images, torch.linalg.inv(seq.c2w).float(), seq.Ks, list(seq.names), masks=mask,
                      viewmats_gt=gt, depths=seq.depths, times=seq.timestamps)


def _slam_cloud(path: Path, cfg: Config) -> SurfelScene:
    """A SLAM system's surfel PLY: positions, normals (required), colours and radii where present."""
    cloud = read_point_ply(path)
    if cloud.normals is None:
        raise DataError(f"{path}: the cloud has no normals (nx ny nz); surfels need them (or leave data.rgbd.cloud "
                        f"empty to fuse the depth frames)")
    _, vertex, names = read_vertex_element(path)
    scales = None
    if "radius" in names:
        r = torch.from_numpy(np.asarray(vertex["radius"], np.float64))
        if not bool(torch.isfinite(r).all()) or bool((r <= 0).any()):
            raise DataError(f"{path}: 'radius' must be positive and finite")
        scales = (cfg.data.rgbd.fusion.scale_factor * r)[:, None].expand(-1, 2).float()
    colours = cloud.colours.float() if cloud.colours is not None else 0.5
    return SurfelScene.from_points(cfg.scene, cloud.points.float(), cloud.normals.float(), scales=scales,
                                   opacities=cfg.data.init_opacity, features=colours)


def estimated(seq: RGBDSequence, cfg: TrackingConfig, progress: bool, init: torch.Tensor | None = None
              ) -> tuple[RGBDSequence, dict[str, Any]]:
    """``seq`` with the trajectory tracked from its frames (:func:`nsplat.data.tracking.track`: every frame, as
    a SLAM system tracks them; the held-out split applies to the refinement), each frame predicted by ``init``'s
    relative motion when given (re-tracking a trajectory), and the tracker's figures (``tracker``,
    ``keyframes``, ``lost``, ``wall_s``, ``cpu_s``, ``fps``). The ground truth is not read."""
    clock = (time.perf_counter(), time.process_time())
    out = track(seq.depths, seq.images, seq.Ks, cfg, init=init, progress=progress, masks=seq.valid)
    wall, cpu = time.perf_counter() - clock[0], time.process_time() - clock[1]
    log.info("tracking: %d frames in %.1f s (%.1f frames/s), %d keyframes, %d lost", len(seq), wall,
             len(seq) / wall, len(out.keyframes), len(out.lost))
    info = {"trajectory": "estimate", "tracker": "nsplat frame-to-model (nsplat.data.tracking)",
            "keyframes": len(out.keyframes), "lost": out.lost, "wall_s": wall, "cpu_s": cpu, "fps": len(seq) / wall}
    return dataclasses.replace(seq, c2w=out.c2w), info


def load_rgbd(src: RGBDSource, cfg: Config, progress: bool = True) -> RefineData:
    """Frames, held-out frames, timeline and the initial scene of an RGB-D source (on the CPU)."""
    root = resolve_data(src.root, DEFAULT_RGBD)
    estimate = src.trajectory == "estimate" or (src.trajectory == "auto" and not (root / "odometry.txt").is_file())
    name = "" if estimate else ("odometry.txt" if src.trajectory == "auto" else src.trajectory)
    if src.layout == "tum":
        files = tum_files(root, name, src.groundtruth, src.max_dt)
    else:
        files = folder_files(root, src.intrinsics_file)
    pick = list(range(0, len(files.color), src.stride))[:src.limit or None]
    if len(pick) < 3:
        raise DataError(f"data.rgbd.stride/limit: {len(pick)} frames left of {len(files.color)}, need at least 3")
    files = dataclasses.replace(
        files, color=[files.color[i] for i in pick], depth=[files.depth[i] for i in pick], c2w=files.c2w[pick],
        c2w_gt=None if files.c2w_gt is None else files.c2w_gt[pick], timestamps=files.timestamps[pick])
    camera = files.camera if files.camera is not None and not src.intrinsics else \
        camera_of(src.camera, src.intrinsics, src.distortion)
    scene = _slam_cloud(resolve(src.cloud), cfg) if src.cloud else None  # checked before any frame is decoded
    depth_camera = camera_of(src.camera, src.depth_intrinsics, []) if src.depth_intrinsics else None
    to_color = depth_to_color_matrix(src.depth_to_color) if src.depth_to_color else None
    seq = load_frames(files, camera, depth_scale=src.depth_scale, depth_range=tuple(src.depth_range),
                      downscale=src.downscale, progress=progress, depth_camera=depth_camera, depth_to_color=to_color)
    source: dict[str, Any] = {"trajectory": name if src.layout == "tum" else "pose files"}
    if not estimate:  # a trajectory estimated from the depth agrees with its scale whatever it is
        check_depth_scale(seq.depths, seq.Ks, seq.c2w, src.depth_scale)
        if seq.c2w_gt is not None and same_trajectory(seq.c2w, seq.c2w_gt):
            log.warning("data.rgbd.trajectory: %s is the ground truth itself (every pose within 1e-6 of %s): "
                        "ATE and RPE measure nothing", source["trajectory"], src.groundtruth)
    split_ = split(len(seq), src.holdout_every)
    if estimate:
        seq, source = estimated(seq, src.tracking, progress)
        return _refine_data(seq, split_, src, cfg, scene, source, progress)
    if not src.retrack:
        return _refine_data(seq, split_, src, cfg, scene, source, progress)
    given = _refine_data(seq, split_, src, cfg, None if scene is None else _slam_cloud(resolve(src.cloud), cfg),
                         source, progress)
    seq, tracked = estimated(seq, src.tracking, progress, init=seq.c2w)
    out = _refine_data(seq, split_, src, cfg, scene, {**source, "retracked": tracked}, progress)
    out.initial = given
    return out


def _refine_data(seq: RGBDSequence, split_: tuple[list[int], list[int]], src: RGBDSource, cfg: Config,
                 scene: SurfelScene | None, source: dict[str, Any], progress: bool) -> RefineData:
    """The training and held-out frames of ``seq`` along its trajectory, its timeline, and ``scene`` (``None``:
    fused from the training frames' depth)."""
    train, held = split_
    tr = seq.subset(train)
    if scene is None:
        s = fuse(tr.depths, tr.images, tr.Ks, tr.c2w, src.fusion, progress=progress)
        scene = SurfelScene.from_points(cfg.scene, s.means, s.normals, scales=s.scales[:, None].expand(-1, 2),
                                        opacities=cfg.data.init_opacity, features=s.colours)
    timeline = Sequence(seq.timestamps, seq.c2w, seq.c2w_gt, train, held, source)
    return RefineData(_views(tr, src.valid), scene, _views(seq.subset(held), src.valid) if held else None, timeline)


def load_data(cfg: Config, device: torch.device, progress: bool = True) -> RefineData:
    """Frames (initial ``viewmats``; ``viewmats_gt`` for the synthetic sources; bool ``masks [B,H,W]``), the
    initial scene and, for ``rgbd``, the held-out frames and the timeline, of ``cfg.data`` (on ``device``)."""
    d = cfg.data
    heldout = sequence = None
    if d.source == "room":
        room = load_room(d.room, resolve(d.cache_dir))
        frames = room.views()
        n = room.means.shape[0]
        scene = SurfelScene.from_points(cfg.scene, room.means, room.normals,
                                        scales=room.scales[:, None].expand(n, 2).contiguous(),
                                        opacities=torch.full((n,), d.init_opacity), features=room.colours)
    elif d.source == "rgbd":
        out = load_rgbd(d.rgbd, cfg, progress)
        if out.initial is not None:
            out.initial = _on(out.initial, device)
        return dataclasses.replace(_on(out, device), initial=out.initial)
    else:
        nf = d.nerf
        views = load_split(resolve_data(nf.root, "nerf_synthetic/lego_400"), nf.split, resolution=nf.resolution,
                           background=cfg.render.background if cfg.scene.channels == 3 else (1.0, 1.0, 1.0),
                           limit=nf.limit or None)
        if not nf.cloud:
            raise ConfigError("data.nerf.cloud: a PLY initial cloud is required for source 'nerf'")
        scene = SurfelScene.load_ply(resolve(nf.cloud), cfg.scene)
        extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
        g = torch.Generator().manual_seed(nf.perturb_seed)
        init = perturb_viewmats(views.viewmats, nf.rot_deg, nf.trans_frac * extent, generator=g)
        masks = torch.ones(views.images.shape[:3], dtype=torch.bool)
        frames = dataclasses.replace(views, masks=masks, viewmats=init.float(), viewmats_gt=views.viewmats)
    return _on(RefineData(frames, scene, heldout, sequence), device)


def _on(data: RefineData, device: torch.device) -> RefineData:
    """``data``'s frames and scene on ``device`` (``initial`` left as it is)."""
    return RefineData(data.frames.to(device), data.scene.to(device),
                      None if data.heldout is None else data.heldout.to(device), data.sequence, data.initial)
