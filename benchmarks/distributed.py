"""Data-parallel scaling: steps per second and held-out PSNR after a fixed number of steps, 1 vs P processes.

Runs the same short ``neural`` job (default: lego at 100², two stage-1 epochs and ``--steps`` stage-2
steps with a global batch of 4 views) once per process count: ``python train.py`` for 1 process and
``torchrun --nproc_per_node=P train.py`` otherwise, each process with ``OMP_NUM_THREADS=1``. The global
batch is the same for every P, so the runs train the same model (to float rounding; docs/distributed.md)
and the held-out PSNR should agree while the step rate scales. Stage-2 time is rank 0's summed step time
(``timing.json``: validation, checkpoints and evaluation excluded); wall time is the whole command.

Prints a Markdown table and writes ``benchmarks/results/distributed.json`` (with the machine's load
average before and after: on a shared machine the 2-process rate is only as good as the idle cores).

    python -m benchmarks.distributed                       # lego 100², 40 steps, 1 and 2 processes
    python -m benchmarks.distributed --procs 1 2 4 --steps 50 neural.batch=8
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import sys
from pathlib import Path

from benchmarks.common import REPO, run_config, write_result

#: The short job (on top of --config): few training and test views, a small hull, two geometry epochs.
SHORT = ["data.train_limit=20", "data.test_limit=5", "geometry.grid=64", "geometry.max_points=6000",
         "geometry.optim.epochs=2", "neural.batch=4", "log.validate=0", "log.images=0", "log.checkpoint=0",
         "log.progress=false", "eval.images=false"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(procs: int, root: Path, args: argparse.Namespace) -> dict:
    """Train with ``procs`` processes into ``root/p<procs>``; returns timings and test metrics."""
    out = root / f"p{procs}"
    launcher = [sys.executable] if procs == 1 else [
        sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={procs}", f"--master_port={_free_port()}"]
    overrides = [f"data.resolution={args.resolution}", f"neural.steps={args.steps}", *SHORT, *args.extra]
    ran = run_config(args.config, out, overrides, env={"OMP_NUM_THREADS": "1"},
                     command=[*launcher, str(REPO / "train.py")], log=root / f"p{procs}.log")
    wall = ran["wall_s"]
    timing = json.loads((out / "timing.json").read_text())
    metrics = json.loads((out / "eval_test" / "metrics.json").read_text())
    return {"processes": procs, "wall_s": wall, "stage1_s": timing["geometry_s"],
            "stage2_s": timing["neural_steps_s"], "steps_per_s": args.steps / timing["neural_steps_s"],
            "test_psnr": metrics["psnr"], "test_ssim": metrics["ssim"], "points": metrics["points"],
            "command": f"train.py --config {args.config} " + " ".join(overrides)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=REPO / "configs" / "lego.yaml")
    p.add_argument("--resolution", type=int, default=100)
    p.add_argument("--steps", type=int, default=40, help="stage-2 steps of every run")
    p.add_argument("--procs", type=int, nargs="+", default=[1, 2], help="process counts to compare")
    p.add_argument("--runs", type=Path, default=REPO / "runs" / "bench-distributed")
    p.add_argument("extra", nargs="*", help="extra config overrides for every run (key=value)")
    args = p.parse_args()
    args.config = args.config.resolve()
    load_before = os.getloadavg()
    rows = [run(n, args.runs, args) for n in args.procs]
    load_after = os.getloadavg()
    base = rows[0]["steps_per_s"]
    lines = [f"{args.config.stem} {args.resolution}², {args.steps} stage-2 steps, global batch of the config "
             f"({' '.join(SHORT + args.extra)}), OMP_NUM_THREADS=1 per process, {os.cpu_count()} cores, "
             f"load average before/after {load_before[0]:.2f}/{load_after[0]:.2f}",
             "", "| processes | stage-2 steps/s | speed-up | stage 1 (s) | wall (s) | test PSNR (dB) | test SSIM |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['processes']} | {r['steps_per_s']:.3f} | {r['steps_per_s'] / base:.2f}× | "
                     f"{r['stage1_s']:.0f} | {r['wall_s']:.0f} | {r['test_psnr']['mean']:.2f} ± "
                     f"{r['test_psnr']['std']:.2f} | {r['test_ssim']['mean']:.4f} |")
    table = "\n".join(lines)
    config = args.config.relative_to(REPO) if args.config.is_relative_to(REPO) else args.config
    write_result("distributed", {"config": str(config), "resolution": args.resolution, "steps": args.steps,
                                 "overrides": SHORT + args.extra, "load_before": load_before,
                                 "load_after": load_after, "rows": rows, "markdown": table}, table)


if __name__ == "__main__":
    main()
