"""Long run of the op's property tests (tests/test_op_properties.py) on many random small scenes.

Draws ``--scenes`` cases from the same generator as the hypothesis test (the documented input
domain of docs/op.md, edges included) with a numpy RNG, runs forward and backward, checks every
property and writes the count, timing and any failures (with the seed that reproduces each) to
``benchmarks/results/properties_soak.json``.

    OMP_NUM_THREADS=1 python benchmarks/properties_soak.py --scenes 10000
    python benchmarks/properties_soak.py --replay 1234      # re-run one failing scene verbosely
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import traceback
from collections import Counter
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from tests.test_op_properties import Draw, check_case, describe, draw_case  # noqa: E402


def run_one(seed: int, max_points: int, max_size: int) -> tuple[list[str], dict]:
    case = draw_case(Draw(rng=np.random.default_rng(seed)), max_points=max_points, max_size=max_size)
    try:
        bad = check_case(case)
    except Exception as exc:  # noqa: BLE001 - an exception is a failure to report, not to crash on
        bad = [f"exception {type(exc).__name__}: {exc}"]
        if os.environ.get("SOAK_TRACEBACK"):
            traceback.print_exc()
    return bad, case


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=10000)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--max-points", type=int, default=10)
    p.add_argument("--max-size", type=int, default=10)
    p.add_argument("--replay", type=int, default=None, help="run only this seed and print the case")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "properties_soak.json")
    args = p.parse_args(argv)
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))  # tests.conftest sets 2
    if args.replay is not None:
        bad, case = run_one(args.replay, args.max_points, args.max_size)
        print(describe(case))
        print("violations:", bad or "none")
        return 1 if bad else 0
    t0, c0 = time.perf_counter(), time.process_time()
    failures, kinds, stats = [], Counter(), Counter()
    for i in range(args.scenes):
        seed = args.first_seed + i
        bad, case = run_one(seed, args.max_points, args.max_size)
        stats[str(case["dtype"]).replace("torch.", "")] += 1
        stats[case["kw"]["composite"]] += 1
        stats[f"N={case['means'].shape[0]}"] += 1
        if bad:
            kinds.update(bad)
            failures.append({"seed": seed, "violations": bad, "case": describe(case)})
            if len(failures) <= 20:
                print(f"seed {seed}: {bad}\n    {describe(case)}", flush=True)
        if (i + 1) % 1000 == 0:
            print(f"{i + 1} scenes, {len(failures)} failing, {time.perf_counter() - t0:.0f}s", flush=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    result = {
        "scenes": args.scenes, "first_seed": args.first_seed, "max_points": args.max_points,
        "max_size": args.max_size, "failing_scenes": len(failures), "violations": dict(kinds),
        "failures": failures[:200], "wall_s": round(wall, 1), "process_time_s": round(cpu, 1),
        "threads": torch.get_num_threads(), "torch": torch.__version__, "machine": platform.machine(),
        "draws": dict(sorted(stats.items())),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"{args.scenes} scenes, {len(failures)} failing ({dict(kinds)}); {wall:.0f}s wall, "
          f"{cpu:.0f}s CPU, {torch.get_num_threads()} thread(s) -> {args.out}")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
