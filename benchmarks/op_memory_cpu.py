"""Peak extra memory of the op's forward + backward on the CPU, per sample slot, against the bound
``2 × pixels·samples·12 bytes + O(N)`` (24 bytes per slot).

Each configuration runs in a fresh subprocess: inputs are built, the extension loaded and a tiny forward
+ backward run (code pages, thread pools), the resident set size is read (baseline), one forward +
backward runs, and the peak resident set size (``VmHWM``) minus the baseline is the op's peak extra
memory (outputs, the backward's per-slot buffers, the per-point order, projection intermediates and
gradients; PyTorch's CPU allocator returns large blocks to the system, so nothing is cached). The O(N)
part (projection, per-point gradients) is measured by the same N at 8×8 pixels and subtracted to give
the per-slot cost, which is compared with the bound's 24 bytes per slot.
``--order sorted`` replaces the native counting sort of the backward's per-point order by the device
sort used on other devices (``nsplat.ops.library._entries_by_point_sorted``) for comparison.
Scene: ``benchmarks/op_cpu.py``'s sphere. Writes ``benchmarks/results/op_memory_cpu.json``.

    python -m benchmarks.op_memory_cpu
    python -m benchmarks.op_memory_cpu --smoke    # one small configuration (CI; not a result)
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from benchmarks.common import REPO, write_result

CONFIGS = [(20_000, 128, 40), (20_000, 256, 40), (100_000, 256, 64), (100_000, 512, 40)]


def _rss_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/self/status")


def one(N: int, res: int, samples: int, order: str) -> dict:
    """Measure one configuration in this process."""
    import torch

    from benchmarks.op_cpu import scene
    from nsplat.ops import library, splat
    from nsplat.ops.build import backend

    backend(torch.device("cpu"))
    if order == "sorted":
        library._entries_by_point = lambda indices, N, nat=None: library._entries_by_point_sorted(indices, N)
    warm, Vw, Kw = scene(1000, 16)
    splat(*[t.clone().requires_grad_() for t in warm], Vw, Kw, 16, 16, samples=4).image.sum().backward()
    params, V, K = scene(N, res)
    ps = [t.clone().requires_grad_() for t in params]
    base = _rss_kb("VmRSS")
    out = splat(*ps, V, K, res, res, samples=samples)
    filled = int((out.indices >= 0).sum())
    out.image.sum().backward()
    peak = _rss_kb("VmHWM")
    slots = res * res * samples
    extra = (peak - base) * 1024
    return dict(N=N, res=res, samples=samples, order=order, slots=slots, filled_slots=filled, extra_bytes=extra)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--one", nargs=4, metavar=("N", "RES", "SAMPLES", "ORDER"), help=argparse.SUPPRESS)
    p.add_argument("--smoke", action="store_true", help="one small configuration (CI; not a result)")
    args = p.parse_args()
    if args.one:
        n, res, m, order = args.one
        print(json.dumps(one(int(n), int(res), int(m), order)))
        return
    def measure(N: int, res: int, m: int, order: str) -> dict:
        out = subprocess.run([sys.executable, "-m", "benchmarks.op_memory_cpu", "--one", str(N), str(res), str(m),
                              order], check=True, capture_output=True, text=True, cwd=REPO)
        return json.loads(out.stdout.strip().splitlines()[-1])

    rows = []
    for N, res, m in [(2_000, 32, 8)] if args.smoke else CONFIGS:
        for order in ("native", "sorted"):
            r = measure(N, res, m, order)
            r["per_point_bytes"] = measure(N, 8, m, order)["extra_bytes"]
            r["bytes_per_slot"] = (r["extra_bytes"] - r["per_point_bytes"]) / r["slots"]
            r["within_bound"] = r["bytes_per_slot"] <= 24.0
            rows.append(r)
    head = ("| N | res | samples | per-point order | filled slots | peak extra MB | of it O(N) MB | bytes per slot "
            "(bound 24) |")
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['N']} | {r['res']}² | {r['samples']} | {r['order']} | "
                     f"{r['filled_slots'] / r['slots']:.0%} | "
                     f"{r['extra_bytes'] / 2**20:.0f} | {r['per_point_bytes'] / 2**20:.0f} | "
                     f"{r['bytes_per_slot']:.1f}{'' if r['within_bound'] else ' (over)'} |")
    table = "\n".join(lines)
    write_result("op_memory_cpu", {"rows": rows, "markdown": table}, table)


if __name__ == "__main__":
    main()
