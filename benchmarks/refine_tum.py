"""Room-scale refinement of a real RGB-D capture: ``configs/refine_tum.yaml`` on TUM RGB-D ``freiburg1_rpy`` (50
frames, a real drifting dense-visual-odometry trajectory and the motion-capture ground truth), before/after.

Runs the config in its own process (so its wall time, CPU time and peak memory are its own, end to end: reading
and fusing the frames, the refinement, fitting and scoring the held-out frames, the outputs), reads the run's
``metrics.json`` and writes ``benchmarks/results/refine_tum-fr1_rpy_50.json`` (320×240;
``refine_tum-fr1_rpy_50-640.json`` with ``--resolution 640``) with the figures the issue names, the CPU and the
run's before/after sheets under ``docs/images/refine_tum/``.

    OMP_NUM_THREADS=2 python -m benchmarks.refine_tum                     # 320×240 (the fast setting)
    OMP_NUM_THREADS=2 python -m benchmarks.refine_tum --resolution 640    # 640×480 (configs/refine_tum_640.yaml)
    python -m benchmarks.refine_tum --set depth_loss=0 --name refine_tum-photometric   # an ablation
    python -m benchmarks.refine_tum --smoke                               # 10 frames at 160×120, 2 steps (CI)

The data: ``$NSPLAT_DATA/rgbd/tum_fr1_rpy_50`` or ``../shared/data/rgbd/tum_fr1_rpy_50``; when missing the script
says so in one line and exits 2.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from benchmarks.common import IMAGES, REPO, RESULTS, markdown, run_config, write_result
from nsplat.data.paths import data_root
from nsplat.tasks.refine.data import DEFAULT_RGBD

CONFIGS = {320: "refine_tum.yaml", 640: "refine_tum_640.yaml"}
#: The run's sheets copied to docs/images/refine_tum/ (the 320×240 run's: the 640×480 ones look alike at 4× the size).
SHEETS = ("heldout_before.png", "heldout_after.png")
#: The smallest run (CI's smoke runs; not a result).
SMOKE = ["optim.steps=2", "heldout.steps=1", "data.rgbd.limit=10", "data.rgbd.downscale=4",
         "data.rgbd.fusion.max_points=5000", "data.rgbd.holdout_every=5"]


def _data() -> Path | None:
    """The data root that holds the sequence (``$NSPLAT_DATA``, else ``../shared/data``), or ``None``."""
    for root in (data_root(), REPO.parent / "shared" / "data"):
        if (root / DEFAULT_RGBD / "rgb.txt").is_file():
            return root
    return None


def summary(m: dict) -> dict:
    """The figures of a run's ``metrics.json`` that the record names at its top level."""
    b, a = m["before"], m["after"]
    out = {"heldout": {f"{k}_{when}": (b if when == "before" else a)["heldout"][k]
                       for k in ("psnr", "ssim", "lpips") for when in ("before", "after")},
           "train": {f"{k}_{when}": (b if when == "before" else a)["train"][k]
                     for k in ("psnr", "ssim", "lpips") for when in ("before", "after")}}
    for k in ("ate_rmse", "rpe_trans_rmse", "rpe_rot_rmse_deg", "points"):
        out[f"{k}_before"], out[f"{k}_after"] = b.get(k), a.get(k)
    out["heldout"]["ssim_gain_pct"] = 100.0 * (a["heldout"]["ssim"] / b["heldout"]["ssim"] - 1.0)
    out["heldout"]["psnr_gain_db"] = a["heldout"]["psnr"] - b["heldout"]["psnr"]
    out["ate_reduction_pct"] = 100.0 * (1.0 - a["ate_rmse"] / b["ate_rmse"])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", type=int, choices=sorted(CONFIGS), default=320)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="further config overrides")
    ap.add_argument("--name", default=None, help="result name (default refine_tum-fr1_rpy_50[-640])")
    ap.add_argument("--smoke", action="store_true", help="the smallest run (CI; not a result)")
    args = ap.parse_args(argv)
    root = _data()
    if root is None:
        print(f"no TUM sequence at {data_root() / DEFAULT_RGBD} (set NSPLAT_DATA to the folder holding "
              f"{DEFAULT_RGBD})", file=sys.stderr)
        return 2
    name = args.name or "refine_tum-fr1_rpy_50" + ("" if args.resolution == 320 else "-640")
    overrides = [*(SMOKE if args.smoke else []), *args.set]
    runs = RESULTS.parent / "runs" if os.environ.get("NSPLAT_BENCH_OUT") else REPO / "runs"
    run_dir = runs / f"bench-{name}"
    cost = run_config(CONFIGS[args.resolution], run_dir, overrides, env={"NSPLAT_DATA": str(root)})
    m = json.loads((run_dir / "metrics.json").read_text())
    s = summary(m)
    record = {**s, "resolution": m["resolution"], "frames": m["frames"], "config": CONFIGS[args.resolution],
              "overrides": overrides, "wall_s": cost["wall_s"], "cpu_s": cost["cpu_s"],
              "peak_rss_gb": m["peak_rss_gb"], "steps": m["steps"], "steps_wall_s": m["steps_wall_s"],
              "steps_cpu_s": m["steps_cpu_s"], "removed": m["removed"], "load": [cost["load_before"],
                                                                                 cost["load_after"]],
              "threads": os.environ.get("OMP_NUM_THREADS"), "before": m["before"], "after": m["after"]}
    out = IMAGES / "refine_tum"
    out.mkdir(parents=True, exist_ok=True)
    for sheet in SHEETS if args.resolution == 320 else ():
        src = run_dir / "before_after" / sheet
        if src.is_file():
            shutil.copyfile(src, out / f"{name}-{sheet}")
    h = s["heldout"]
    rows = [["held-out PSNR (dB)", f"{h['psnr_before']:.2f}", f"{h['psnr_after']:.2f}", f"{h['psnr_gain_db']:+.2f} dB"],
            ["held-out SSIM", f"{h['ssim_before']:.4f}", f"{h['ssim_after']:.4f}", f"{h['ssim_gain_pct']:+.1f} %"],
            ["train PSNR (dB)", f"{s['train']['psnr_before']:.2f}", f"{s['train']['psnr_after']:.2f}", ""],
            ["train SSIM", f"{s['train']['ssim_before']:.4f}", f"{s['train']['ssim_after']:.4f}", ""],
            ["ATE RMSE (cm)", f"{100 * s['ate_rmse_before']:.2f}", f"{100 * s['ate_rmse_after']:.2f}",
             f"{-s['ate_reduction_pct']:+.1f} %"],
            ["RPE trans. RMSE (mm)", f"{1000 * s['rpe_trans_rmse_before']:.2f}",
             f"{1000 * s['rpe_trans_rmse_after']:.2f}", ""],
            ["RPE rot. RMSE (deg)", f"{s['rpe_rot_rmse_deg_before']:.3f}", f"{s['rpe_rot_rmse_deg_after']:.3f}", ""]]
    table = markdown(["", "before (SLAM start)", "after", "change"], rows)
    table += (f"\n\n{m['resolution'][0]}×{m['resolution'][1]}, {m['steps']} steps: {cost['wall_s'] / 60:.1f} min wall, "
              f"{cost['cpu_s'] / 60:.1f} min CPU, peak RSS {m['peak_rss_gb']:.2f} GB")
    write_result(name, record, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
