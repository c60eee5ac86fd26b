"""Speed and memory of the splatting op on CUDA (issue 3), with the CPU op and gsplat's 2DGS rasteriser.

Measures, on one camera of a sphere of surfels (one float32 scene per N, scales shrinking as 1/sqrt(N) so the
depth complexity per pixel stays about constant):
  * forward (``splat``: projection + tree build + sampling + compositing) and backward time, median of
    ``--reps`` runs after a warm-up, and the sampling stage alone (tree build + per-pixel SPS);
  * peak extra GPU memory of one forward+backward (``torch.cuda.max_memory_allocated`` minus what was
    allocated before), also as a multiple of pixels·samples·12 bytes (the issue's bound is 2× plus O(N));
  * sweeps over N (10k–4M, 512², m=16), resolution (256²–1920×1080, N=1M, m=16) and samples (1–64,
    N=1M, 512²), and the log-log slopes of time vs N and vs pixels;
  * CUDA vs the CPU op at a small size (N=30k, 256², m=16; the CPU op uses all of the machine's cores);
  * gsplat's ``rasterization_2dgs`` on the same surfels and camera, forward+backward, where gsplat imports
    (its CUDA code is JIT-compiled on first use; ``--gsplat off`` skips it).

Usage (on a machine with a CUDA device):
    python -m benchmarks.op_cuda                 # full sweep → benchmarks/results/op_cuda.json + a table
    python -m benchmarks.op_cuda --quick         # a few small points (smoke test)
``--device cpu --tiny --out /tmp/x.json`` exercises the script without a GPU (tiny sizes, no memory figures,
no gsplat); its numbers are not results.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import platform
import statistics
import sys
import time
import traceback
from functools import partial
from pathlib import Path

import torch

from benchmarks.common import RESULTS, machine
from nsplat.ops import project, sample, splat, tangent_frame

MB = 2**20


def sphere_scene(N: int, device: torch.device, seed: int = 0) -> dict[str, torch.Tensor]:
    """N surfels on the unit sphere (outward normals), tangent std-devs ~ the mean spacing, RGB features."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(N, 3, generator=g)
    means = d / d.norm(dim=1, keepdim=True)
    spacing = math.sqrt(4 * math.pi / N)
    scales = spacing * (0.6 + 0.8 * torch.rand(N, 2, generator=g))
    opacities = 0.5 + 0.5 * torch.rand(N, generator=g)
    features = torch.rand(N, 3, generator=g)
    sc = dict(means=means, normals=means.clone(), scales=scales, opacities=opacities, features=features)
    return {k: v.to(device) for k, v in sc.items()}


def camera(width: int, height: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """One camera 3 units from the sphere's centre looking at it; the sphere spans ~80% of the shorter side."""
    V = torch.eye(4)
    V[2, 3] = 3.0
    f = 1.13 * min(width, height)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return V[None].to(device), K[None].to(device)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device: torch.device):
    sync(device)
    t = time.perf_counter()
    out = fn()
    sync(device)
    return out, time.perf_counter() - t


def measure_nsplat(N: int, width: int, height: int, samples: int, device: torch.device, reps: int) -> dict:
    """Median forward / backward / sampling-only times (ms) and peak extra memory of forward+backward."""
    sc = sphere_scene(N, device)
    V, K = camera(width, height, device)
    weights = torch.rand(1, height, width, 3, generator=torch.Generator().manual_seed(1)).to(device)
    leaves = [sc[k].clone().requires_grad_() for k in ("means", "normals", "scales", "opacities", "features")]

    def forward():
        return splat(*leaves, V, K, width, height, samples=samples, seed=0)

    def backward(out):
        return torch.autograd.grad((out.image * weights).sum(), leaves)

    out = forward()  # warm-up (and first-use build)
    backward(out)
    del out
    peak = None
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        out = forward()
        backward(out)
        del out
        peak = torch.cuda.max_memory_allocated(device) - base
    fwd, bwd, smp = [], [], []
    for _ in range(reps):
        out, t_f = timed(forward, device)
        _, t_b = timed(partial(backward, out), device)
        del out
        fwd.append(t_f)
        bwd.append(t_b)
    with torch.no_grad():
        proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10,
                       lowpass=1.0)
        for _ in range(reps):
            res, t_s = timed(lambda: sample(proj, K, width, height, samples=samples, seed=0), device)
            smp.append(t_s)
        filled = float((res[0] >= 0).float().mean())
        work = float(res[3].float().mean())
    pixels = width * height
    row = dict(N=N, width=width, height=height, pixels=pixels, samples=samples,
               fwd_ms=1e3 * statistics.median(fwd), bwd_ms=1e3 * statistics.median(bwd),
               sample_ms=1e3 * statistics.median(smp), filled_slots=filled, mean_evaluations=work)
    row["total_ms"] = row["fwd_ms"] + row["bwd_ms"]
    if peak is not None:
        row["peak_extra_MB"] = peak / MB
        row["peak_over_pixels_samples_12B"] = peak / (pixels * samples * 12)
    return row


def quat_from_frame(t0: torch.Tensor, t1: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions of the rotations whose columns are (t0, t1, n) (right-handed orthonormal frames)."""
    R = torch.stack([t0, t1, n], dim=-1)  # [N, 3, 3], columns
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    w = 0.5 * torch.sqrt(torch.clamp(1 + m00 + m11 + m22, min=0))
    x = 0.5 * torch.sqrt(torch.clamp(1 + m00 - m11 - m22, min=0))
    y = 0.5 * torch.sqrt(torch.clamp(1 - m00 + m11 - m22, min=0))
    z = 0.5 * torch.sqrt(torch.clamp(1 - m00 - m11 + m22, min=0))
    x = torch.copysign(x, R[:, 2, 1] - R[:, 1, 2])
    y = torch.copysign(y, R[:, 0, 2] - R[:, 2, 0])
    z = torch.copysign(z, R[:, 1, 0] - R[:, 0, 1])
    q = torch.stack([w, x, y, z], dim=-1)
    return q / q.norm(dim=-1, keepdim=True)


def measure_gsplat(N: int, width: int, height: int, device: torch.device, reps: int) -> dict:
    """gsplat 2DGS forward/backward on the same surfels and camera (RGB, no sampling: all splats per tile)."""
    from gsplat import rasterization_2dgs

    sc = sphere_scene(N, device)
    V, K = camera(width, height, device)
    t0, t1 = tangent_frame(sc["normals"])
    quats = quat_from_frame(t0, t1, sc["normals"])
    scales = torch.cat([sc["scales"], torch.zeros_like(sc["scales"][:, :1])], dim=1)
    weights = torch.rand(1, height, width, 3, generator=torch.Generator().manual_seed(1)).to(device)
    # colors per camera ([C, N, 3]): gsplat 1.5.3's 2DGS path does not broadcast [N, 3] colours over cameras
    leaves = [t.clone().requires_grad_() for t in (sc["means"], quats, scales, sc["opacities"], sc["features"][None])]

    def forward():
        return rasterization_2dgs(*leaves, V, K, width, height)[0]

    def backward(img):
        return torch.autograd.grad((img * weights).sum(), leaves)

    backward(forward())
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    backward(forward())
    peak = torch.cuda.max_memory_allocated(device) - base
    fwd, bwd = [], []
    for _ in range(reps):
        img, t_f = timed(forward, device)
        _, t_b = timed(lambda: backward(img), device)
        fwd.append(t_f)
        bwd.append(t_b)
    row = dict(N=N, width=width, height=height, fwd_ms=1e3 * statistics.median(fwd),
               bwd_ms=1e3 * statistics.median(bwd), peak_extra_MB=peak / MB)
    row["total_ms"] = row["fwd_ms"] + row["bwd_ms"]
    return row


def loglog_slope(xs: list[float], ys: list[float]) -> float:
    lx, ly = [math.log(x) for x in xs], [math.log(y) for y in ys]
    mx, my = sum(lx) / len(lx), sum(ly) / len(ly)
    return sum((a - mx) * (b - my) for a, b in zip(lx, ly)) / sum((a - mx) ** 2 for a in lx)


def table(rows: list[dict], cols: list[tuple[str, str, str]]) -> str:
    head = "| " + " | ".join(c[1] for c in cols) + " |"
    sep = "|" + "|".join("---:" for _ in cols) + "|"
    body = ["| " + " | ".join(format(r[c[0]], c[2]) if r.get(c[0]) is not None else "–" for c in cols) + " |"
            for r in rows]
    return "\n".join([head, sep, *body])


COLS = [("N", "N", ","), ("width", "W", "d"), ("height", "H", "d"), ("samples", "m", "d"),
        ("fwd_ms", "forward ms", ".1f"), ("bwd_ms", "backward ms", ".1f"), ("total_ms", "fwd+bwd ms", ".1f"),
        ("sample_ms", "sampling ms", ".1f"), ("peak_extra_MB", "peak extra MB", ".0f"),
        ("peak_over_pixels_samples_12B", "peak / (P·m·12 B)", ".2f"), ("mean_evaluations", "kernel evals/px", ".0f")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few small configurations")
    ap.add_argument("--tiny", action="store_true", help="tiny configurations, to check the script itself")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--gsplat", choices=("auto", "off"), default="auto")
    ap.add_argument("--sections", default="N,res,m,cpu,gsplat",
                    help="comma-separated subset of N (sweep over N), res, m, cpu (CUDA vs CPU), gsplat")
    ap.add_argument("--out", default=str(RESULTS / "op_cuda.json"))
    args = ap.parse_args(argv)
    sections = set(args.sections.split(","))
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("op_cuda: no CUDA device; run this on a GPU machine (or --device cpu --quick to test the script)")
        return 2
    if args.tiny:
        n_sweep, res_sweep, m_sweep = [1_000, 3_000], [(48, 48), (96, 64)], [1, 4]
        mid_n, cpu_case, gs_sizes, base = 2_000, (1_000, 32, 32, 4), [1_000], (64, 64)
    elif args.quick:
        n_sweep, res_sweep, m_sweep = [10_000, 100_000], [(256, 256), (512, 512)], [1, 16]
        mid_n, cpu_case, gs_sizes, base = 100_000, (10_000, 128, 128, 8), [100_000], (512, 512)
    else:
        n_sweep = [10_000, 30_000, 100_000, 300_000, 1_000_000, 2_000_000, 4_000_000]
        res_sweep = [(256, 256), (512, 512), (1024, 1024), (1920, 1080)]
        m_sweep = [1, 4, 16, 64]
        mid_n, cpu_case, gs_sizes, base = 1_000_000, (30_000, 256, 256, 16), [100_000, 1_000_000, 4_000_000], (512, 512)

    result: dict = dict(
        command="python -m benchmarks.op_cuda" + (" " + " ".join(argv if argv is not None else sys.argv[1:])).rstrip(),
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        torch=torch.__version__, python=platform.python_version(), reps=args.reps,
        device=torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu",
        cpu_threads=torch.get_num_threads(), dtype="float32", scene="unit sphere of N surfels, one camera at 3",
        machine=machine())
    if device.type == "cuda":
        result["cuda"] = torch.version.cuda

    def run(tag, N, W, H, m):
        row = measure_nsplat(N, W, H, m, device, args.reps)
        print(f"[{tag}] " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
              flush=True)
        return row

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def save() -> None:
        """Writes what is measured so far (a run stopped at a time limit keeps its finished sections)."""
        out.write_text(json.dumps(result, indent=2) + "\n")

    result["vs_N"] = [run("N", N, *base, 16) for N in n_sweep] if "N" in sections else []
    save()
    result["vs_resolution"] = [run("res", mid_n, W, H, 16) for W, H in res_sweep] if "res" in sections else []
    save()
    result["vs_samples"] = [run("m", mid_n, *base, m) for m in m_sweep] if "m" in sections else []
    result["slopes"] = {}
    if len(result["vs_N"]) > 1:
        result["slopes"]["time_vs_N"] = loglog_slope([r["N"] for r in result["vs_N"]],
                                                     [r["total_ms"] for r in result["vs_N"]])
    if len(result["vs_resolution"]) > 1:
        result["slopes"]["time_vs_pixels"] = loglog_slope([r["pixels"] for r in result["vs_resolution"]],
                                                          [r["total_ms"] for r in result["vs_resolution"]])
    save()
    if "cpu" in sections:
        cpu_vs_device(result, cpu_case, device, args.reps)
        save()
    gs = measure_gsplat_rows(result, gs_sizes, base, device, args,
                             run) if "gsplat" in sections else {"skipped": "not asked"}
    result["gsplat_2dgs"] = gs
    targets(result, gs)
    save()
    report(result, args, gs)
    return 0


def cpu_vs_device(result: dict, cpu_case: tuple[int, int, int, int], device: torch.device, reps: int) -> None:
    """CUDA vs CPU at a small size (the CPU op on all cores of this machine)."""
    N, W, H, m = cpu_case
    cpu_row = measure_nsplat(N, W, H, m, torch.device("cpu"), max(1, min(reps, 3)))
    dev_row = measure_nsplat(N, W, H, m, device, reps)
    result["cpu_vs_cuda"] = dict(case=dict(N=N, width=W, height=H, samples=m), cpu=cpu_row, device=dev_row,
                                 speedup_total=cpu_row["total_ms"] / dev_row["total_ms"],
                                 speedup_sampling=cpu_row["sample_ms"] / dev_row["sample_ms"])
    print(f"[cpu] {cpu_row['total_ms']:.1f} ms vs {dev_row['total_ms']:.1f} ms: "
          f"x{result['cpu_vs_cuda']['speedup_total']:.1f}", flush=True)


def measure_gsplat_rows(result: dict, gs_sizes: list[int], base: tuple[int, int], device: torch.device,
                        args: argparse.Namespace, run) -> dict:
    """gsplat 2DGS side by side with nsplat (m=16) at each N of ``gs_sizes``; the error when gsplat fails."""
    gs: dict = {}
    if args.gsplat == "off" or device.type != "cuda":
        gs["skipped"] = "disabled" if args.gsplat == "off" else "needs a CUDA device"
        return gs
    try:
        import gsplat

        gs["version"] = gsplat.__version__
        t = time.perf_counter()
        gs["rows"] = []
        for N in gs_sizes:
            g_row = measure_gsplat(N, *base, device, args.reps)
            if not gs["rows"]:
                g_row["first_call_s_including_jit"] = time.perf_counter() - t
            ours = next((r for r in result["vs_N"] if r["N"] == N), None) or run("gs-ref", N, *base, 16)
            g_row["nsplat_total_ms_m16"] = ours["total_ms"]
            g_row["nsplat_over_gsplat"] = ours["total_ms"] / g_row["total_ms"]
            gs["rows"].append(g_row)
            print(f"[gsplat] N={N}: {g_row['total_ms']:.1f} ms, nsplat/gsplat = {g_row['nsplat_over_gsplat']:.2f}",
                  flush=True)
    except Exception as exc:  # record why the comparison is missing instead of failing the benchmark
        gs["error"] = f"{type(exc).__name__}: {exc}"
        gs["traceback"] = traceback.format_exc(limit=6)
        print(f"[gsplat] unavailable: {gs['error']}", flush=True)
    return gs


def targets(result: dict, gs: dict) -> None:
    """The issue's targets at 1M surfels, 512², m=16, one camera (where the sweeps measured them)."""
    target = next((r for r in result["vs_N"] if r["N"] == 1_000_000), None)
    if target is None:
        return
    slopes = result["slopes"]
    t = dict(case="N=1M, 512², m=16", total_ms=target["total_ms"], slope_N=slopes.get("time_vs_N"),
             slope_pixels=slopes.get("time_vs_pixels"),
             slopes_ok=max(slopes.values()) <= 1.1 if slopes else None)
    if "peak_over_pixels_samples_12B" in target:
        t["peak_over_pixels_samples_12B"] = target["peak_over_pixels_samples_12B"]
    g1 = next((r for r in gs.get("rows", []) if r["N"] == 1_000_000), None)
    if g1 is not None:
        t["nsplat_over_gsplat"] = g1["nsplat_over_gsplat"]
        t["within_1_5x_of_gsplat"] = g1["nsplat_over_gsplat"] <= 1.5
    result["targets"] = t


def report(result: dict, args: argparse.Namespace, gs: dict) -> None:
    """Prints the tables of whatever sections ran."""
    print(f"\n{result['device']}, torch {result['torch']}, median of {args.reps}; wrote {args.out}\n")
    for name in ("vs_N", "vs_resolution", "vs_samples"):
        if result[name]:
            print(f"### {name}\n\n{table(result[name], COLS)}\n")
    for name, slope in result["slopes"].items():
        print(f"log-log slope of fwd+bwd {name.replace('_', ' ')}: {slope:.2f}")
    c = result.get("cpu_vs_cuda")
    if c:
        print(f"CPU ({result['cpu_threads']} threads) vs {args.device} at N={c['case']['N']}, "
              f"{c['case']['width']}x{c['case']['height']}, m={c['case']['samples']}: "
              f"{c['cpu']['total_ms']:.1f} ms vs {c['device']['total_ms']:.1f} ms fwd+bwd (x{c['speedup_total']:.1f})")
    if gs.get("rows"):
        base = gs["rows"][0]
        print(f"\n### gsplat 2DGS, {base['width']}x{base['height']}, same surfels\n")
        print(table(gs["rows"], [("N", "N", ","), ("fwd_ms", "gsplat fwd ms", ".1f"),
                                 ("bwd_ms", "gsplat bwd ms", ".1f"),
                                 ("total_ms", "gsplat fwd+bwd ms", ".1f"), ("peak_extra_MB", "gsplat peak MB", ".0f"),
                                 ("nsplat_total_ms_m16", "nsplat fwd+bwd ms (m=16)", ".1f"),
                                 ("nsplat_over_gsplat", "nsplat / gsplat", ".2f")]))
    else:
        print(f"gsplat 2DGS: {gs.get('error') or gs.get('skipped')}")


if __name__ == "__main__":
    sys.exit(main())
