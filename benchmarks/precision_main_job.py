"""The main job (``python train.py``, configs/default.yaml) with each ``neural.precision``: held-out test PSNR/SSIM
and the stage-2 time (the 500 training steps, ``timing.json`` ``neural_steps_s``), on this CPU.

Each run is its own ``train.py`` process (:func:`benchmarks.common.run_config`); the precisions alternate, so a
change in the machine's load hits them alike. Stage 1 is the same for both precisions (it has no network); its
time is reported as the control. A run is deterministic, so ``--seeds`` (the run seed: data order, features, op
samples) tells a precision's effect on quality from a seed's; ``--repeats`` only repeats the timing. Runs under
``runs/precision_main_job/``.

    python -m benchmarks.precision_main_job --seeds 0 1 2        # float32 and bfloat16 per seed (~9 min)

Writes ``benchmarks/results/precision_main_job.json``.
"""
from __future__ import annotations

import argparse
import json
import statistics

from benchmarks.common import REPO, markdown, run_config, write_result

PRECISIONS = ("float32", "bfloat16")


def one(precision: str, seed: int, repeat: int) -> dict:
    """Train the main job with ``neural.precision=precision`` and ``seed``; its metrics and times."""
    run = REPO / "runs" / "precision_main_job" / f"{precision}-seed{seed}-{repeat}"
    proc = run_config("default.yaml", run, [f"neural.precision={precision}", f"seed={seed}"])
    metrics = json.loads((run / "eval_test" / "metrics.json").read_text())
    timing = json.loads((run / "timing.json").read_text())
    return {"precision": precision, "seed": seed, "repeat": repeat, "test_psnr": metrics["psnr"]["mean"],
            "test_ssim": metrics["ssim"]["mean"], "stage2_s": timing["neural_steps_s"],
            "stage1_s": timing["geometry_s"], "eval_render_s": metrics["render_seconds"], "wall_s": proc["wall_s"],
            "cpu_s": proc["cpu_s"], "load_before": proc["load_before"], "load_after": proc["load_after"],
            "run": str(run.relative_to(REPO))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--repeats", type=int, default=1)
    args = p.parse_args()
    rows = []
    for r in range(args.repeats):
        for i, seed in enumerate(args.seeds):
            for precision in (PRECISIONS if (r + i) % 2 == 0 else PRECISIONS[::-1]):
                rows.append(one(precision, seed, r))
    table = markdown(["precision", "seed", "repeat", "test PSNR dB", "SSIM", "stage 2 s", "stage 1 s", "test render s",
                      "process wall s", "process CPU s", "load before → after"],
                     [[r["precision"], r["seed"], r["repeat"], f"{r['test_psnr']:.2f}", f"{r['test_ssim']:.4f}",
                       f"{r['stage2_s']:.1f}", f"{r['stage1_s']:.1f}", f"{r['eval_render_s']:.2f}", f"{r['wall_s']:.0f}",
                       f"{r['cpu_s']:.0f}", f"{r['load_before'][0]:.1f} → {r['load_after'][0]:.1f}"] for r in rows])
    means = {p: {k: statistics.mean(r[k] for r in rows if r["precision"] == p) for k in ("test_psnr", "stage2_s")}
             for p in PRECISIONS}
    table += "".join(f"\n{p}: mean test PSNR {m['test_psnr']:.2f} dB, mean stage 2 {m['stage2_s']:.1f} s"
                     for p, m in means.items())
    write_result("precision_main_job", {"config": "configs/default.yaml", "rows": rows, "means": means}, table)


if __name__ == "__main__":
    main()
