"""The record of a reconstruction run at the paper's own setting (``configs/reconstruct_paper.yaml``).

The run itself is a plain, resumable ``train.py`` run (about 3.5 hours on 2 CPU cores; it checkpoints every epoch):

    OMP_NUM_THREADS=2 python train.py --config configs/reconstruct_paper.yaml --run runs/paper/bunny
    python train.py --run runs/paper/bunny --resume            # after an interruption
    python -m benchmarks.reconstruct_paper runs/paper/bunny     # once it has finished

This script reads the finished run folder and writes ``benchmarks/results/reconstruct-paper-<shape>.json``: the run's
``metrics.json`` (distances, held-out PSNR, wall and CPU seconds over every segment), the validation trajectory and
the points moved by each repositioning check (TensorBoard), and where the final points lie: the share farther than
``--far`` of the GT's bounding-box diagonal from the GT, split into points hidden inside the surface and floaters
outside it, with the median albedo of each and of the near points (dark floaters vanish against the black
background, so the image loss leaves them where they are).
"""
from __future__ import annotations

import argparse
import json
import types
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from benchmarks.common import markdown, write_result
from nsplat.config import load_config, read_yaml
from nsplat.data.pointclouds import load_shape
from nsplat.evaluation.shape_metrics import bbox_diagonal
from nsplat.tasks import reconstruct


def point_spread(points: np.ndarray, albedo: np.ndarray, gt: np.ndarray, gt_normals: np.ndarray,
                 far: float) -> dict[str, float]:
    """Where ``points [N,3]`` (albedo ``[N,3]``) lie against ``gt [M,3]`` (outward normals ``gt_normals [M,3]``).

    Returns ``{far_share, far_albedo, near_albedo, inside_share, inside_albedo, outside_share, outside_albedo,
    p50, p90, p99}``: distances to the nearest GT point in units of the GT's bounding-box diagonal; ``far``: the
    distance beyond which a point counts as far; a far point is inside (hidden in the volume) or outside (a floater)
    by the side of its nearest GT point's normal; the albedos are medians of the RGB norm, NaN for an empty set;
    the shares are of all points."""
    dist, nearest = cKDTree(gt).query(points)
    d = dist / bbox_diagonal(gt)
    bright = np.linalg.norm(albedo, axis=1)
    is_far = d > far
    inside = ((points - gt[nearest]) * gt_normals[nearest]).sum(axis=1) < 0
    groups = {"far": is_far, "near": ~is_far, "inside": is_far & inside, "outside": is_far & ~inside}
    out = {f"{k}_share": float(m.mean()) for k, m in groups.items() if k != "near"}
    out |= {f"{k}_albedo": float(np.median(bright[m])) if m.any() else float("nan") for k, m in groups.items()}
    return out | {f"p{q}": float(np.quantile(d, q / 100)) for q in (50, 90, 99)}


def trajectory(run_dir: Path) -> dict[str, list]:
    """``{step, chamfer, hausdorff, moved}`` from the run's TensorBoard log (``moved``: points moved per check)."""
    ea = EventAccumulator(str(run_dir / "tb"))
    ea.Reload()
    tags = ea.Tags()["scalars"]
    pick = {"chamfer": "shape/chamfer", "hausdorff": "shape/hausdorff"}
    out: dict[str, list] = {k: [e.value for e in ea.Scalars(t)] for k, t in pick.items() if t in tags}
    out["step"] = [e.step for e in ea.Scalars("shape/chamfer")] if "shape/chamfer" in tags else []
    out["moved"] = [int(e.value) for e in ea.Scalars("epoch/moved")] if "epoch/moved" in tags else []
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a finished run folder of configs/reconstruct_paper.yaml")
    p.add_argument("--far", type=float, default=0.05, help="distance (GT diagonals) beyond which a point is far")
    args = p.parse_args()
    if not (args.run / "metrics.json").is_file():
        raise SystemExit(f"run: {args.run} has no metrics.json; finish it first (train.py --run {args.run} --resume)")
    metrics = json.loads((args.run / "metrics.json").read_text())
    cfg = load_config(reconstruct.Config, read_yaml(args.run / "config.yaml"))
    pc = load_shape(cfg.data.shape, cfg.data.root or None)
    scene = reconstruct.restore(cfg, types.SimpleNamespace(run_dir=args.run, device=torch.device("cpu")))
    spread = point_spread(scene.means.detach().double().numpy(), scene.features.detach().double().numpy(),
                          pc.points.double().numpy(), pc.normals.double().numpy(), args.far)
    traj = trajectory(args.run)
    since, steps = metrics.get("train_cpu_since_step", 0), metrics["epochs"] * -(-metrics["views"] // cfg.optim.batch)
    row = [metrics["shape"], f"{metrics['chamfer']:.4f}", f"{metrics['hausdorff']:.3f}",
           f"{metrics['heldout_psnr']:.2f} dB",
           f"{spread['far_share']:.0%} ({spread['inside_share']:.0%} / {spread['outside_share']:.0%})",
           f"{spread['inside_albedo']:.2f} / {spread['outside_albedo']:.2f} / {spread['near_albedo']:.2f}",
           sum(traj["moved"]), f"{metrics['train_seconds'] / 3600:.2f} h",
           f"{metrics['train_cpu_seconds'] / 3600:.2f} h (steps {since + 1}–{steps})"]
    table = markdown(["shape", "Chamfer", "Hausdorff", "held-out PSNR",
                      f"points > {args.far} diag (inside / outside)", "albedo inside / outside / near",
                      "points moved", "steps' wall", "steps' CPU"], [row])
    write_result(f"reconstruct-paper-{metrics['shape']}",
                 {"run": str(args.run), "metrics": metrics, "far": args.far, "spread": spread, "trajectory": traj},
                 table)


if __name__ == "__main__":
    main()
