"""The GPU targets of issue 57 against what one `.ci/gpu_check.sh` run measured: the table it ends with.

    python -m benchmarks.gpu_targets --lego OUT/results/gpu_lego-cuda.json --train OUT/results/gpu_lego_train-X.json \
        --main-job-s 17.2 --op OUT/op_cuda.json --name gpu_targets-h200

Reads the step table of ``benchmarks.gpu_lego`` (one and eight views at 200²), the validation curve of the lego run
(``tools.val_curve``: the best val PSNR reached within 180 s), the main job's wall time and the gsplat rows of
``benchmarks.op_cuda`` (nsplat / gsplat at each N; the worst counts). A missing input leaves its row "not measured".
Writes ``benchmarks/results/<name>.json`` and prints the Markdown table.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.common import write_result
from benchmarks.targets import evaluate, gsplat_ratio, psnr_within, read, step_ms, table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lego", type=Path, help="benchmarks.gpu_lego's JSON")
    ap.add_argument("--train", type=Path, help="tools.val_curve's JSON of the lego run")
    ap.add_argument("--main-job-s", type=float, default=None, help="the main job's wall time (s)")
    ap.add_argument("--op", type=Path, help="benchmarks.op_cuda's JSON")
    ap.add_argument("--name", default="gpu_targets", help="result name (benchmarks/results/<name>.json)")
    args = ap.parse_args(argv)
    if args.main_job_s is not None and args.main_job_s <= 0:
        ap.error(f"--main-job-s: expected seconds > 0, got {args.main_job_s}")
    lego = read(args.lego)
    values = [step_ms(lego, 1), step_ms(lego, 8), psnr_within(read(args.train), 180.0), args.main_job_s,
              gsplat_ratio(read(args.op))]
    rows = evaluate(values)
    write_result(args.name, {"rows": rows, "inputs": {k: str(v) for k, v in vars(args).items()}}, table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
