"""A synthetic RGB-D sequence in the TUM layout, ray-traced from the synthetic room (:mod:`nsplat.tasks.refine.room`):
8-bit RGB and 16-bit depth PNGs, ``rgb.txt``/``depth.txt``, the exact trajectory as ``groundtruth.txt`` and a
drifting estimate of it as ``odometry.txt`` (in its own frame: the first camera at the origin), as real odometry
writes it."""
from __future__ import annotations

import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from nsplat.cameras import intrinsics_from_fov
from nsplat.data.tum_format import write_trajectory
from nsplat.tasks.refine.room import render_frame, room_primitives, trajectory

#: Frame rate of the synthetic sequence (stamps ``t0 + i / FPS``).
FPS = 30.0
T0 = 1000.0


def drift(c2w: torch.Tensor, rot_deg: float, trans: float, seed: int = 0) -> torch.Tensor:
    """A drifting estimate of ``c2w [F,4,4]``: the true relative motions, each followed by a random rotation of
    ``rot_deg`` degrees and a random translation of ``trans`` metres, chained from the first pose."""
    g = torch.Generator().manual_seed(seed)
    out = [c2w[0].clone()]
    for i in range(1, c2w.shape[0]):
        rel = torch.linalg.inv(c2w[i - 1]) @ c2w[i]
        axis = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
        a = math.radians(rot_deg)
        Kx = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]],
                          dtype=torch.float64)
        noise = torch.eye(4, dtype=torch.float64)
        noise[:3, :3] = torch.eye(3, dtype=torch.float64) + math.sin(a) * Kx + (1 - math.cos(a)) * Kx @ Kx
        noise[:3, 3] = trans * torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
        out.append(out[-1] @ rel @ noise)
    est = torch.stack(out)
    return torch.linalg.inv(est[0]) @ est  # its own frame: the first camera at the origin


def write_sequence(folder: Path, frames: int = 8, width: int = 48, height: int = 36, fov_deg: float = 70.0,
                   rot_deg: float = 0.6, trans: float = 0.01) -> dict[str, object]:
    """Write the sequence to ``folder``; returns its ``intrinsics`` (OpenCV convention, ``[fx, fy, cx, cy]``), the
    true ``c2w [F,4,4]`` and the ``odometry [F,4,4]``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "rgb").mkdir(exist_ok=True)
    (folder / "depth").mkdir(exist_ok=True)
    V = trajectory(frames)
    K = intrinsics_from_fov(fov_deg, width, height)[0].double()
    prims = room_primitives()
    stamps = [T0 + i / FPS for i in range(frames)]
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for i, (s, v) in enumerate(zip(stamps, V)):
        f = render_frame(prims, v, K, width, height, supersample=2)
        depth = torch.where(torch.isfinite(f["depth"]) & f["valid"], f["depth"], torch.zeros_like(f["depth"]))
        iio.imwrite(folder / "rgb" / f"{s:.6f}.png", (f["image"].numpy() * 255 + 0.5).astype(np.uint8))
        iio.imwrite(folder / "depth" / f"{s + 0.002:.6f}.png", (depth.numpy() * 5000 + 0.5).astype(np.uint16))
        rgb_lines.append(f"{s:.6f} rgb/{s:.6f}.png")
        depth_lines.append(f"{s + 0.002:.6f} depth/{s + 0.002:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    c2w = torch.linalg.inv(V)
    odo = drift(c2w, rot_deg, trans)
    write_trajectory(folder / "groundtruth.txt", np.array(stamps) - 0.003, c2w, "ground truth")
    write_trajectory(folder / "odometry.txt", np.array(stamps) + 0.001, odo, "odometry")
    intr = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) - 0.5, float(K[1, 2]) - 0.5]
    return {"intrinsics": intr, "c2w": c2w, "odometry": odo}
