"""Validation PSNR against training wall time of one ``train.py`` run folder, finished or stopped (a time limit).

Reads the run's ``geometry_history.json`` (stage 1: ``geometry.log.validate``) and ``history.json`` (stage 2:
``log.validate``), written at every validation, so a run killed by a time limit keeps the points it reached
(:func:`benchmarks.common.run_curve`: the training seconds exclude the validation renders; stage 2's are
offset by stage 1's time when the run finished it), with the test metrics when the run got that far.

    timeout 300 python train.py --config configs/lego.yaml --device cuda --run-dir /tmp/lego \\
        geometry.log.validate=720 log.validate=125
    python -m tools.val_curve /tmp/lego --name gpu_lego_train-h200 --wall-s 300

Writes ``benchmarks/results/<name>.json`` and prints the curve as a table.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.common import markdown, run_curve, write_result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="the run folder (train.py --run-dir)")
    ap.add_argument("--name", required=True, help="the result's name (benchmarks/results/<name>.json)")
    ap.add_argument("--wall-s", type=float, default=None, help="the run's wall-clock limit or time, recorded")
    ap.add_argument("--command", default=None, help="the training command, recorded")
    args = ap.parse_args()
    rec = run_curve(args.run)
    if not rec["curve"]:
        print(f"{args.run}: no validation recorded (geometry.log.validate / log.validate, or the run stopped "
              "before the first one)", file=sys.stderr)
    rows = [["stage 1" if i < rec["stage1_points"] else "stage 2", f"{t:.1f}", f"{p:.2f}"]
            for i, (t, p) in enumerate(rec["curve"])]
    table = markdown(["stage", "training s (without validation)", "val PSNR (dB)"], rows)
    table += (f"\n\nfinished: {rec['finished']}; stage-1 test PSNR: {rec['stage1_test_psnr']}; "
              f"test PSNR: {rec['test_psnr']}")
    write_result(args.name, {"run": str(args.run), "command": args.command, "wall_s": args.wall_s, **rec}, table)
    return 0 if rec["curve"] else 1


if __name__ == "__main__":
    sys.exit(main())
