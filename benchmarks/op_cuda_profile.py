"""Where the CUDA op's time goes: per-kernel GPU time of one forward+backward (torch.profiler, CUPTI).

Runs ``splat`` forward + backward on the sphere scene of :mod:`benchmarks.op_cuda` (one camera, float32) for
each requested size, after a warm-up, under ``torch.profiler`` and prints the kernels sorted by total GPU
time, with the share of the whole; ``--out`` writes them as JSON.

Usage (on a machine with a CUDA device):
    python -m benchmarks.op_cuda_profile --sizes 10000,1000000 --out benchmarks/results/op_cuda_profile.json
"""
from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from benchmarks.common import machine
from benchmarks.op_cuda import camera, sphere_scene
from nsplat.ops import splat


def profile_case(N: int, width: int, height: int, samples: int, reps: int) -> dict:
    """Per-kernel GPU time (ms per forward+backward) of ``reps`` profiled iterations."""
    dev = torch.device("cuda")
    sc = sphere_scene(N, dev)
    V, K = camera(width, height, dev)
    weights = torch.rand(1, height, width, 3, device=dev)
    leaves = [sc[k].clone().requires_grad_() for k in ("means", "normals", "scales", "opacities", "features")]

    def step():
        out = splat(*leaves, V, K, width, height, samples=samples, seed=0)
        torch.autograd.grad((out.image * weights).sum(), leaves)

    step()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(reps):
            step()
        torch.cuda.synchronize()
    rows = []
    for e in prof.key_averages():
        dev_us = getattr(e, "self_device_time_total", None)
        if dev_us is None:
            dev_us = e.self_cuda_time_total
        if dev_us > 0 and e.device_type == torch.autograd.DeviceType.CUDA:
            rows.append(dict(name=e.key[:90], ms=dev_us / 1e3 / reps, calls=e.count // reps))
    rows.sort(key=lambda r: -r["ms"])
    total = sum(r["ms"] for r in rows)
    for r in rows:
        r["share"] = r["ms"] / total if total else 0.0
    return dict(N=N, width=width, height=height, samples=samples, gpu_ms_total=total, kernels=rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="10000,1000000", help="comma-separated N")
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("op_cuda_profile: no CUDA device")
        return 2
    result = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  device=torch.cuda.get_device_name(), torch=torch.__version__, machine=machine(), cases=[])
    for N in (int(s) for s in args.sizes.split(",")):
        case = profile_case(N, args.width, args.height, args.samples, args.reps)
        result["cases"].append(case)
        print(f"\n### N={N:,}, {args.width}x{args.height}, m={args.samples}: "
              f"{case['gpu_ms_total']:.2f} ms GPU time per forward+backward\n")
        print("| kernel | ms | calls | share |\n|---|---:|---:|---:|")
        for r in case["kernels"][:25]:
            print(f"| `{r['name']}` | {r['ms']:.3f} | {r['calls']} | {100 * r['share']:.1f} % |")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
