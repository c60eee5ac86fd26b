"""The main job (``python train.py``, configs/default.yaml) with each ``neural.precision``: held-out test PSNR/SSIM
and the stage-2 time (the 500 training steps, ``timing.json`` ``neural_steps_s``), on this CPU.

Each run is its own ``train.py`` process (:func:`benchmarks.common.run_config`); the precisions alternate, so a
change in the machine's load hits them alike. Stage 1 is the same in every run (it has no network); its time is
reported as the control. Runs under ``runs/precision_main_job/``.

    python -m benchmarks.precision_main_job                      # float32 and bfloat16, once each (~7 min)
    python -m benchmarks.precision_main_job --repeats 2

Writes ``benchmarks/results/precision_main_job.json``.
"""
from __future__ import annotations

import argparse
import json

from benchmarks.common import REPO, markdown, run_config, write_result

PRECISIONS = ("float32", "bfloat16")


def one(precision: str, repeat: int) -> dict:
    """Train the main job with ``neural.precision=precision``; its metrics and times."""
    run = REPO / "runs" / "precision_main_job" / f"{precision}-{repeat}"
    proc = run_config("default.yaml", run, [f"neural.precision={precision}"])
    metrics = json.loads((run / "eval_test" / "metrics.json").read_text())
    timing = json.loads((run / "timing.json").read_text())
    return {"precision": precision, "repeat": repeat, "test_psnr": metrics["psnr"]["mean"],
            "test_ssim": metrics["ssim"]["mean"], "stage2_s": timing["neural_steps_s"],
            "stage1_s": timing["geometry_s"], "eval_render_s": metrics["render_seconds"], "wall_s": proc["wall_s"],
            "cpu_s": proc["cpu_s"], "load_before": proc["load_before"], "load_after": proc["load_after"],
            "run": str(run.relative_to(REPO))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=1)
    args = p.parse_args()
    rows = []
    for r in range(args.repeats):
        for precision in (PRECISIONS if r % 2 == 0 else PRECISIONS[::-1]):
            rows.append(one(precision, r))
    table = markdown(["precision", "repeat", "test PSNR dB", "SSIM", "stage 2 s", "stage 1 s", "test render s",
                      "process wall s", "process CPU s", "load before → after"],
                     [[r["precision"], r["repeat"], f"{r['test_psnr']:.2f}", f"{r['test_ssim']:.4f}",
                       f"{r['stage2_s']:.1f}", f"{r['stage1_s']:.1f}", f"{r['eval_render_s']:.2f}", f"{r['wall_s']:.0f}",
                       f"{r['cpu_s']:.0f}", f"{r['load_before'][0]:.1f} → {r['load_after'][0]:.1f}"] for r in rows])
    write_result("precision_main_job", {"config": "configs/default.yaml", "rows": rows}, table)


if __name__ == "__main__":
    main()
