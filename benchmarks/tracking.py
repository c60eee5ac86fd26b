"""The RGB-D tracker (:mod:`nsplat.data.tracking`) on the shared TUM sequences, against Open3D's frame-to-frame
hybrid RGB-D odometry (``compute_rgbd_odometry`` with ``RGBDOdometryJacobianFromHybridTerm``, default options:
the "well-kept library" row) on the same frames, when ``open3d`` imports (``pip install -e '.[rgbd]'``).

Each sequence is read as the refine task reads it (``nsplat.data.rgbd``: undistorted, ``--downscale`` 2 gives
320×240, the Freiburg-1 preset), every frame tracked from the frames alone; the ground truth only scores: ATE RMSE
after an SE(3) alignment and RPE over consecutive frames (:mod:`nsplat.tasks.refine.trajectory`). Time is the
tracking alone (frames already decoded), wall and CPU.

Writes ``benchmarks/results/tracking.json`` and prints a Markdown table. The data: ``$NSPLAT_DATA`` or
``../shared/data``; a missing sequence is skipped with one line.

    OMP_NUM_THREADS=2 python -m benchmarks.tracking                        # tum_fr1_rpy_50 and tum_fr1_rpy_10hz
    python -m benchmarks.tracking --sequences tum_fr1_rpy_50 --limit 20    # a small run
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.common import REPO, markdown, write_result
from nsplat.data.paths import data_root
from nsplat.data.rgbd import RGBDSequence, camera_of, load_frames, tum_files
from nsplat.data.tracking import TrackingConfig, track
from nsplat.tasks.refine.trajectory import ate, rpe


def _root() -> Path:
    for root in (data_root(), REPO.parent / "shared" / "data"):
        if (root / "rgbd").is_dir():
            return root
    return data_root()


def load(name: str, downscale: int, limit: int) -> RGBDSequence:
    """The sequence's frames with the ground truth (frames paired as the refine task pairs them)."""
    files = tum_files(_root() / "rgbd" / name, "", "groundtruth.txt", 0.02)
    if limit:
        files = dataclasses.replace(files, color=files.color[:limit], depth=files.depth[:limit],
                                    c2w=files.c2w[:limit], c2w_gt=files.c2w_gt[:limit],
                                    timestamps=files.timestamps[:limit])
    return load_frames(files, camera_of("fr1", [], []), depth_scale=5000.0, depth_range=(0.1, 5.0),
                       downscale=downscale, progress=False)


def _score(c2w: torch.Tensor, seq: RGBDSequence, wall: float, cpu: float, **extra: Any) -> dict[str, Any]:
    a, r = ate(c2w, seq.c2w_gt), rpe(c2w, seq.c2w_gt)
    return {"frames": len(seq), "ate_rmse": a["rmse"], "rpe_trans_rmse": r["trans_rmse"],
            "rpe_rot_rmse_deg": r["rot_rmse_deg"], "wall_s": wall, "cpu_s": cpu, "fps": len(seq) / wall, **extra}


def ours(seq: RGBDSequence, rounds: int) -> dict[str, Any]:
    clock = (time.perf_counter(), time.process_time())
    out = track(seq.depths, seq.images, seq.Ks, TrackingConfig(rounds=rounds), progress=False, masks=seq.valid)
    return _score(out.c2w, seq, time.perf_counter() - clock[0], time.process_time() - clock[1],
                  tracker=f"nsplat frame-to-model, {rounds} re-alignment rounds", lost=len(out.lost),
                  keyframes=len(out.keyframes))


def open3d_f2f(seq: RGBDSequence) -> dict[str, Any] | None:
    """Open3D's frame-to-frame hybrid odometry, chained; ``None`` when open3d does not import."""
    try:
        import open3d as o3d
    except ImportError:
        return None
    B, H, W = seq.depths.shape
    K = seq.Ks[0].double()
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) - 0.5,
                                             float(K[1, 2]) - 0.5)

    def rgbd(k: int) -> Any:
        depth = torch.where(seq.valid[k], seq.depths[k], torch.zeros_like(seq.depths[k]))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image((seq.images[k].numpy() * 255).round().astype(np.uint8)),
            o3d.geometry.Image(depth.numpy().astype(np.float32)), depth_scale=1.0, depth_trunc=5.0,
            convert_rgb_to_intensity=True)

    clock = (time.perf_counter(), time.process_time())
    poses, fails, prev = [np.eye(4)], 0, rgbd(0)
    for k in range(1, B):
        cur = rgbd(k)
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            cur, prev, intr, np.eye(4), o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(),
            o3d.pipelines.odometry.OdometryOption())
        fails += 0 if ok else 1
        poses.append(poses[-1] @ (T if ok else np.eye(4)))
        prev = cur
    return _score(torch.from_numpy(np.stack(poses)), seq, time.perf_counter() - clock[0],
                  time.process_time() - clock[1], tracker=f"Open3D {o3d.__version__} frame-to-frame hybrid",
                  lost=fails)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", nargs="+", default=["tum_fr1_rpy_50", "tum_fr1_rpy_10hz"])
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--limit", type=int, default=0, help="the first frames only (0: all)")
    ap.add_argument("--rounds", type=int, default=TrackingConfig().rounds)
    ap.add_argument("--out", default="tracking")
    args = ap.parse_args()
    rows, table = [], []
    for name in args.sequences:
        if not (_root() / "rgbd" / name).is_dir():
            print(f"{name}: skipped (no {_root() / 'rgbd' / name}; nsplat data fetch)")
            continue
        seq = load(name, args.downscale, args.limit)
        for res in (ours(seq, 0), ours(seq, args.rounds), open3d_f2f(seq)):
            if res is None:
                continue
            res = {"sequence": name, "resolution": [seq.width, seq.height], **res}
            rows.append(res)
            table.append([name, res["tracker"], res["frames"], f"{100 * res['ate_rmse']:.1f}",
                          f"{100 * res['rpe_trans_rmse']:.2f}", f"{res['rpe_rot_rmse_deg']:.2f}", res["lost"],
                          f"{res['fps']:.1f}", f"{res['cpu_s']:.0f}"])
    write_result(args.out, {"rows": rows}, markdown(
        ["sequence", "tracker", "frames", "ATE RMSE (cm)", "RPE trans (cm)", "RPE rot (°)", "lost", "frames/s",
         "CPU s"], table))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
