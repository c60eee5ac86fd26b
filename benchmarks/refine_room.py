"""Pose and scene refinement on the synthetic room: before/after pose error, PSNR/SSIM, time, memory.

Runs the ``refine`` task (configs/refine_room.yaml, with the size overrides below) once per
gradient estimator (``ht`` and ``sampled``), each in its own process (so peak RSS is per run), then
prints a table, writes ``benchmarks/results/refine_room.json`` and before/after images to
``docs/images/refine/``.

    OMP_NUM_THREADS=2 python -m benchmarks.refine_room [--steps 150] [--width 64 --height 48]
        [--estimators ht sampled] [--set key=value ...] [--name refine_room]

Pose errors are reported three ways (:func:`nsplat.tasks.refine.poses.pose_report`): absolute against the ground truth,
after removing the rigid offset common to all cameras (with a learnable scene, scene and cameras can
move together without changing any image; docs/results.md measures how much of that offset is this
gauge freedom), and as relative pose errors over all camera pairs (no fitted alignment at all).

``--set`` passes further config overrides to both runs (the same budget for every estimator). Runs of
estimators not named this time are kept in the JSON when its arguments match (so the estimators can
be run in separate invocations, e.g. in parallel).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from benchmarks.common import IMAGES as ALL_IMAGES
from benchmarks.common import REPO as ROOT
from benchmarks.common import read_result, run_config, write_result
from nsplat.config import read_yaml
from nsplat.tasks.refine.room import RoomSpec, load_room

IMAGES = ALL_IMAGES / "refine"


def run_one(estimator: str, args: argparse.Namespace) -> dict:
    run_dir = ROOT / "runs" / f"bench-{args.name.replace('_', '-')}-{estimator}"
    overrides = [f"render.estimator={estimator}", f"optim.steps={args.steps}",
                 f"data.room.width={args.width}", f"data.room.height={args.height}",
                 f"data.room.frames={args.frames}", f"optim.decay_every={args.steps // 3}",
                 f"filter.start={args.steps // 5}", f"filter.every={args.steps // 3}",
                 f"log.checkpoint={args.steps}", *args.set]
    run_config(ROOT / "configs" / "refine_room.yaml", run_dir, ["--device", "cpu", *overrides])
    init = json.loads((run_dir / "metrics_initial.json").read_text())
    final = json.loads((run_dir / "metrics_final.json").read_text())
    return {"run_dir": str(run_dir.relative_to(ROOT)), "initial": init, "final": final, "overrides": overrides}


def save_images(run_dir: Path, prefix: str, tag: str, frames: list[int]) -> None:
    cfg = read_yaml(run_dir / "config.yaml")
    spec = RoomSpec(**cfg["data"]["room"])
    room = load_room(spec, ROOT / cfg["data"]["cache_dir"])
    before = torch.load(run_dir / "renders_initial.pt")
    after = torch.load(run_dir / "renders_final.pt")
    IMAGES.mkdir(parents=True, exist_ok=True)
    for f in frames:
        ref = room.images[f] * room.masks[f, ..., None]
        row = torch.cat([ref, before[f].clamp(0, 1), after[f].clamp(0, 1),
                         (before[f] - room.images[f]).abs().clamp(0, 1), (after[f] - room.images[f]).abs().clamp(0,
                                                                                                                 1)], 1)
        big = row.repeat_interleave(3, 0).repeat_interleave(3, 1)
        iio.imwrite(IMAGES / f"{prefix}_{tag}_frame{f:02d}.png", (big.numpy() * 255).round().astype(np.uint8))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--height", type=int, default=48)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--estimators", nargs="+", default=["ht", "sampled"])
    p.add_argument("--set", nargs="*", default=[], help="extra config overrides for every run")
    p.add_argument("--name", default="refine_room",
                   help="study name: results in benchmarks/results/<name>.json, runs in runs/bench-<name>-<estimator>")
    args = p.parse_args()
    prefix = "room" if args.name == "refine_room" else args.name
    key = {k: v for k, v in vars(args).items() if k not in ("estimators", "name")}
    out = {"args": key, "runs": {}}
    results = {}
    for est in args.estimators:
        results[est] = run_one(est, args)
        save_images(ROOT / results[est]["run_dir"], prefix, est, [0, args.frames // 2])
    old = read_result(args.name)  # re-read now: another invocation may have written meanwhile
    if old is not None and old.get("args") == key:
        out["runs"].update(old.get("runs", {}))
    out["runs"].update(results)
    write_result(args.name, out)
    hdr = (f"{'estimator':>9} | {'rot° before':>11} {'after':>7} {'÷':>5} | "
           f"{'trans before':>12} {'after':>7} {'÷':>5} | "
           f"{'PSNR b/a':>13} | {'SSIM b/a':>13} {'+%':>6} | {'pts b/a':>11} | {'time s':>7} | {'RSS MB':>7}")
    print(hdr)
    print("-" * len(hdr))
    rows = []
    for est, r in out["runs"].items():
        i, f = r["initial"], r["final"]
        rows.append(f"{est:>9} | " + " | ".join(
            f"{i[k]:.4f} → {f[k]:.4f} (÷{i[k] / f[k]:.1f})" for k in
            ("rot_deg_aligned", "trans_aligned", "rpe_rot_deg", "rpe_trans") if k in i and k in f)
            + f" | common offset after: {f.get('gauge_rot_deg', float('nan')):.3f}° / "
              f"{f.get('gauge_trans', float('nan')):.4f}")
        print(f"{est:>9} | {i['rot_deg']:11.3f} {f['rot_deg']:7.3f} {i['rot_deg'] / f['rot_deg']:5.1f} | "
              f"{i['trans']:12.4f} {f['trans']:7.4f} {i['trans'] / f['trans']:5.1f} | "
              f"{i['psnr']:6.2f}/{f['psnr']:6.2f} | {i['ssim']:6.3f}/{f['ssim']:6.3f} "
              f"{100 * (f['ssim'] / i['ssim'] - 1):6.1f} | {i['points']:5d}/{f['points']:5d} | "
              f"{f['seconds']:7.1f} | {f['peak_rss_mb']:7.0f}")
    print("\npose errors without the common offset, before → after: rot° aligned | trans aligned | RPE rot° | "
          "RPE trans")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
