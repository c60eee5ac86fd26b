"""Stage-1 levers on lego 200² (issue 28): which settings make the point-only fit learn faster per step.

Each variant is ``configs/lego.yaml``'s stage 1 alone (``neural.steps=0``) shortened to 6 epochs of the 60
training views (360 Adam steps of one view, the learning-rate milestones scaled with it), with the fitted
surfels rendered on 5 val views every 60 steps; one variant changes one setting of the shipped stage 1
(``combo``: the three that won, together). Runs go to ``runs/s1probe/<variant>`` (a finished run is not
trained again), one after another, pinned with ``--cpus``.

    python benchmarks/stage1_levers.py --cpus 0                 # all variants, one thread on core 0
    python benchmarks/stage1_levers.py --report                 # table + JSON of the finished runs

Output: a table on stdout and ``benchmarks/results/stage1_levers-lego.json`` (val PSNR per 60 steps,
stage wall time without the validation renders, test PSNR of the final surfels, wall/CPU of the command).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LR = "geometry.optim.learn={{means: {m}, normals: 0.01, scales: 0.005, opacities: 0.05, features: {f}}}"
#: ``eval.draws=1``: every variant's val/test PSNR is of one op draw (the runs before ``render_views`` could
#: average draws were; the ranking, not the absolute level, is what this table is for).
BASE = ["neural.steps=0", "geometry.optim.epochs=6", "geometry.log.validate=60", "log.progress=false", "eval.draws=1"]
#: Round 1 starts from the stage 1 shipped before it (``ht``, std = the 3-NN spacing, 1 px² low-pass).
OLD = ["render.estimator=ht", "geometry.scale_factor=1.0", "render.lowpass=1.0"]
#: Round 2 starts from round 1's ``combo`` (RGB colour; the SH3 colour it selected came into
#: ``configs/lego.yaml`` after it, and ``neural.view_colour`` with it).
R2 = ["geometry.optim.shading=none", "geometry.sh_degree=0", "neural.view_colour=false"]
#: variant → overrides of the shipped stage 1. Round 1 (``base`` … ``combo``): one change to the old stage
#: 1; ``combo`` (its three winners) became the shipped stage 1. Round 2 (``r2-*``): one change to that.
VARIANTS: dict[str, list[str]] = {
    "base": OLD,
    "sampled": [*OLD, "render.estimator=sampled"],
    "sh3": [*OLD, "geometry.optim.shading=sh", "geometry.sh_degree=3"],
    "flr01": [*OLD, LR.format(m=0.002, f=0.01)],
    "ssim02": [*OLD, "geometry.optim.ssim_weight=0.2"],
    "mlr5e-4": [*OLD, LR.format(m=0.0005, f=0.05)],
    "mlr5e-3": [*OLD, LR.format(m=0.005, f=0.05)],
    "scale05": [*OLD, "geometry.scale_factor=0.5"],
    "scale03": [*OLD, "geometry.scale_factor=0.3"],
    "lowpass03": [*OLD, "render.lowpass=0.3"],
    "combo": [*OLD, "render.estimator=sampled", "geometry.scale_factor=0.5", "render.lowpass=0.3"],
    "r2-base": [*R2],
    "r2-m16": [*R2, "render.samples=16"],
    "r2-m24": [*R2, "render.samples=24"],
    "r2-m64": [*R2, "render.samples=64"],
    "r2-m96": [*R2, "render.samples=96"],
    "r2-sh1": [*R2, "geometry.optim.shading=sh", "geometry.sh_degree=1"],
    "r2-sh3-rest0.05": [*R2, "geometry.optim.shading=sh", "geometry.sh_degree=3",
                        "geometry.optim.sh_rest_lr=0.05"],
    "r2-sh1-rest0.2": [*R2, "geometry.optim.shading=sh", "geometry.sh_degree=1",
                       "geometry.optim.sh_rest_lr=0.2"],
    "r2-ht": [*R2, "render.estimator=ht"],
    "r2-ht-pips": [*R2, "render.estimator=ht-pips"],
    "r2-truncated": [*R2, "render.renderer=truncated"],
    "r2-grid200": [*R2, "geometry.grid=200", "geometry.max_points=160000"],
}


def run_one(name: str, cpus: str | None) -> None:
    run = REPO / "runs" / "s1probe" / name
    if (run / "timing.json").is_file():
        return
    cmd = [sys.executable, "train.py", "--config", "configs/lego.yaml", "--run", str(run), "--overwrite", *BASE,
           *VARIANTS[name]]
    env = dict(os.environ)
    if cpus:
        cmd = ["taskset", "-c", cpus, *cmd]
        env["OMP_NUM_THREADS"] = str(len(cpus.split(",")))
    t0, cpu0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{name} failed:\n{proc.stderr[-3000:]}")
    (run / "command.json").write_text(json.dumps({
        "command": cmd, "wall_s": time.perf_counter() - t0, "threads": env.get("OMP_NUM_THREADS"),
        "cpu_s": (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)}, indent=1))


def summary(name: str) -> dict | None:
    run = REPO / "runs" / "s1probe" / name
    if not (run / "timing.json").is_file():
        return None
    hist = json.loads((run / "geometry_history.json").read_text())["history"]
    geo = json.loads((run / "eval_geometry.json").read_text())
    cmd = json.loads((run / "command.json").read_text()) if (run / "command.json").is_file() else {}
    return {"variant": name, "overrides": VARIANTS[name], "points": geo["points"],
            "curve": [(h["step"], h["elapsed_s"], h["val_psnr"]) for h in hist],
            "val_psnr_final": geo["val"]["psnr"]["mean"], "test_psnr": geo["test"]["psnr"]["mean"], **cmd}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS), metavar="NAME")
    p.add_argument("--cpus", default=None, help="pin runs to these cores, one thread each (e.g. 0)")
    p.add_argument("--report", action="store_true", help="only tabulate the finished runs")
    args = p.parse_args()
    if not args.report:
        for name in args.variants:
            run_one(name, args.cpus)
    rows = [r for name in VARIANTS if (r := summary(name)) is not None]
    steps = [s for s, _, _ in rows[0]["curve"]] if rows else []
    print("| variant | " + " | ".join(f"val @{s}" for s in steps) + " | stage s (360 steps) | threads | test |")
    print("|---" * (len(steps) + 4) + "|")
    for r in rows:
        print(f"| {r['variant']} | " + " | ".join(f"{v:.2f}" for _, _, v in r["curve"]) +
              f" | {r['curve'][-1][1]:.0f} | {r.get('threads') or 2} | {r['test_psnr']:.2f} |")
    out = REPO / "benchmarks" / "results" / "stage1_levers-lego.json"
    out.write_text(json.dumps({"scene": "lego 200x200, 60 train views", "runs": rows}, indent=1))


if __name__ == "__main__":
    main()
