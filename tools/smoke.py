"""CI smoke test of the benchmarks and tools: every script that can run at its smallest size in under a minute runs
once.

Each command of :data:`SMOKE` runs as its own process from the repository root with ``NSPLAT_BENCH_OUT`` set to a
temporary folder, so nothing under ``benchmarks/results/`` or ``docs/images/`` changes; its numbers are not
results. A command that needs the data sets (:data:`NEEDS_DATA`) is skipped, and says so, when ``$NSPLAT_DATA``
does not hold them.

    python -m tools.smoke                   # every smoke command (1-2 minutes on 2 cores)
    python -m tools.smoke benchmarks.op_cpu # some of them
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from benchmarks.common import REPO
from nsplat.data.paths import data_root

#: Script (its module) → the arguments of its smallest run.
SMOKE: dict[str, list[str]] = {
    "tools.allocation_table": ["--check"],
    "benchmarks.op_cpu": ["--smoke", "--repeats", "1"],
    "benchmarks.op_memory_cpu": ["--smoke"],
    "benchmarks.op_cuda": ["--device", "cpu", "--tiny", "--reps", "1", "--gsplat", "off", "--sections", "N,res,m"],
    "benchmarks.estimators": ["--scenes", "random", "--composites", "additive", "--ms", "4", "--groups", "4",
                              "--per-group", "5"],
    "tools.properties_soak": ["--scenes", "20", "--no-edges"],
    "benchmarks.tradeoff": ["--tiny"],
    "benchmarks.network_levers": ["--sizes", "64", "--reps", "1", "--compile-reps", "0"],
    "benchmarks.gpu_lego": ["--device", "cpu", "--quick"],
    "benchmarks.gt_views": ["--smoke"],
    "benchmarks.refine_memory": ["--smoke"],
    "benchmarks.fusion_scaling": ["--smoke"],
    "benchmarks.refine_tum": ["--smoke"],
    "benchmarks.refine_drift": ["--smoke"],
    "benchmarks.tracking": ["--sequences", "tum_fr1_rpy_50", "--limit", "6", "--rounds", "0"],
    "benchmarks.scenes": ["--smoke"],
}
#: Scripts that read a data set (relative to ``$NSPLAT_DATA``).
NEEDS_DATA = {"benchmarks.tradeoff": "dss_pointclouds", "benchmarks.gt_views": "dss_pointclouds",
              "benchmarks.refine_tum": "rgbd/tum_fr1_rpy_50", "benchmarks.refine_drift": "rgbd/tum_fr1_rpy_50",
              "benchmarks.tracking": "rgbd/tum_fr1_rpy_50"}
#: Seconds one smoke command may take.
TIMEOUT_S = 120


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scripts", nargs="*", metavar="SCRIPT", help=f"some of {', '.join(SMOKE)} (default: all)")
    args = p.parse_args()
    unknown = sorted(set(args.scripts) - set(SMOKE))
    if unknown:
        p.error(f"no smoke run for {', '.join(unknown)}; expected some of {', '.join(SMOKE)}")
    failed = []
    with tempfile.TemporaryDirectory(prefix="nsplat-bench-smoke-") as out:
        env = {**os.environ, "NSPLAT_BENCH_OUT": out}
        for name in args.scripts or list(SMOKE):
            if name in NEEDS_DATA and not (data_root() / NEEDS_DATA[name]).is_dir():
                print(f"{name}: skipped (needs {data_root() / NEEDS_DATA[name]}; nsplat data fetch)", flush=True)
                continue
            cmd = [sys.executable, "-m", name, *SMOKE[name]]
            t0 = time.perf_counter()
            try:
                proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
                ok, tail = proc.returncode == 0, (proc.stdout + proc.stderr)[-2000:]
            except subprocess.TimeoutExpired:
                ok, tail = False, f"timed out after {TIMEOUT_S} s"
            print(f"{name}: {'ok' if ok else 'FAILED'} in {time.perf_counter() - t0:.0f} s "
                  f"(python -m {name} {' '.join(SMOKE[name])})", flush=True)
            if not ok:
                failed.append(name)
                print(tail, flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
