"""CPU op benchmark: forward+backward time and peak memory vs N, resolution and samples; speed-up over the
dense oracle; log-log slopes.

    python -m benchmarks.op_cpu            # full sweep (N 1k–1M, 32²–512², samples 1–64), ~10 min on 2 cores
    python -m benchmarks.op_cpu --quick    # small sweep
    python -m benchmarks.op_cpu --smoke    # one tiny configuration of each sweep (CI)

Scene: N surfels covering a unit sphere (tangent std-dev 0.7× the point spacing, opacity 0.8, RGB features)
seen from distance 3 with a 50° field of view, so both the front and the back layer project into the image.
Each configuration runs in a fresh subprocess (peak RSS is per configuration); timings are the median of
`--repeats` runs after one warm-up, wall clock with all cores (torch threads = cores) and process CPU time.
The dense oracle is O(N·pixels) in time and memory, so it is timed on a band of image rows and scaled by
the pixel ratio (stated in the output). Writes benchmarks/results/op_cpu.json (:mod:`benchmarks.common`).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time

from benchmarks.common import REPO, write_result


def scene(N: int, res: int):
    import torch

    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=-1)
    spacing = math.sqrt(4 * math.pi / N)
    f = 0.5 * res / math.tan(math.radians(25.0))
    V = torch.eye(4)[None].clone()
    V[0, 2, 3] = 3.0
    K = torch.tensor([[[f, 0.0, res / 2], [0.0, f, res / 2], [0.0, 0.0, 1.0]]])
    params = [d.clone(), d.clone(), torch.full((N, 2), 0.7 * spacing), torch.full((N,), 0.8),
              torch.rand(N, 3, generator=g)]
    return params, V, K


def one(N: int, res: int, samples: int, repeats: int, dense_rows: int) -> dict:
    """Measure one configuration in this process; returns a JSON-able dict."""

    from nsplat.ops import splat, splat_dense

    params, V, K = scene(N, res)

    def step(fn):
        ps = [t.clone().requires_grad_() for t in params]
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn(ps)
        w1 = time.perf_counter()
        out.image.sum().backward()
        w2, c2 = time.perf_counter(), time.process_time()
        return w1 - w0, w2 - w1, c2 - c0, out

    step(lambda ps: splat(*ps, V, K, res, res, samples=samples))
    runs = [step(lambda ps: splat(*ps, V, K, res, res, samples=samples, seed=r)) for r in range(repeats)]
    fwd = statistics.median(r[0] for r in runs)
    bwd = statistics.median(r[1] for r in runs)
    cpu = statistics.median(r[2] for r in runs)
    work = float(runs[-1][3].work.float().mean())
    row = dict(N=N, res=res, samples=samples, fwd_s=fwd, bwd_s=bwd, total_s=fwd + bwd, cpu_s=cpu,
               work_per_pixel=work, peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    if dense_rows:
        rows = min(dense_rows, res)
        Kb = K.clone()
        Kb[0, 1, 2] -= (res - rows) / 2  # the central band of `rows` rows of the same camera
        t = [step(lambda ps: splat_dense(*ps, V, Kb, res, rows)) for _ in range(2)]
        dense = statistics.median(x[0] + x[1] for x in t) * res / rows
        row.update(dense_s_extrapolated=dense, dense_rows=rows, speedup_vs_dense=dense / (fwd + bwd))
    return row


def run_sub(N: int, res: int, samples: int, repeats: int, dense_rows: int = 0) -> dict:
    cmd = [sys.executable, "-m", "benchmarks.op_cpu", "--one", str(N), str(res), str(samples), str(repeats),
           str(dense_rows)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO)
    return json.loads(out.stdout.strip().splitlines()[-1])


def slope(xs: list[float], ys: list[float]) -> float:
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)


def table(rows: list[dict], key: str) -> str:
    head = f"| {key} | fwd s | bwd s | fwd+bwd s | CPU s | evals/px | peak RSS MB |"
    lines = [head, "|" + "---|" * 7]
    for r in rows:
        lines.append(f"| {r[key]} | {r['fwd_s']:.3f} | {r['bwd_s']:.3f} | {r['total_s']:.3f} | {r['cpu_s']:.3f} | "
                     f"{r['work_per_pixel']:.0f} | {r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--smoke", action="store_true", help="one tiny configuration per sweep (CI; not a result)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--one", nargs=5, type=int, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        print(json.dumps(one(*args.one)))
        return 0
    target_n, target_res = 20000, 128
    if args.smoke:
        Ns, ress, samples, target_n, target_res = [500, 1000], [16, 32], [1, 8], 1000, 32
    elif args.quick:
        Ns, ress, samples = [1000, 4000, 16000], [32, 64, 128], [1, 8, 40]
    else:
        Ns, ress, samples = [1000, 4000, 16000, 64000, 256000, 1000000], [32, 64, 128, 256, 512], [1, 4, 16, 40, 64]
    target = run_sub(target_n, target_res, 40, args.repeats, dense_rows=16)
    by_n = [run_sub(n, target_res, 40, args.repeats) for n in Ns]
    by_res = [run_sub(target_n, r, 40, args.repeats) for r in ress]
    by_m = [run_sub(target_n, target_res, m, args.repeats) for m in samples]
    big_n = by_n[-3:]  # the slope over the three largest N (small N is dominated by fixed costs)
    result = dict(
        target=target, by_N=by_n, by_resolution=by_res, by_samples=by_m,
        slope_time_vs_N=slope([r["N"] for r in big_n], [r["total_s"] for r in big_n]),
        slope_time_vs_pixels=slope([r["res"] ** 2 for r in by_res], [r["total_s"] for r in by_res]),
    )
    write_result("op_cpu", result)
    print(f"target N={target_n} {target_res}² samples=40: fwd+bwd {target['total_s']:.3f}s "
          f"(CPU {target['cpu_s']:.3f}s), "
          f"dense {target['dense_s_extrapolated']:.1f}s (from {target['dense_rows']} rows) → "
          f"speed-up {target['speedup_vs_dense']:.0f}×")
    print("\nvs N (128², samples 40)\n" + table(by_n, "N"))
    print("\nvs resolution (N 20000, samples 40)\n" + table(by_res, "res"))
    print("\nvs samples (N 20000, 128²)\n" + table(by_m, "samples"))
    print(f"\nlog-log slope of fwd+bwd time: vs N (3 largest N) {result['slope_time_vs_N']:.2f}, "
          f"vs pixels {result['slope_time_vs_pixels']:.2f}; load average during the run {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
