"""Sampler benchmark on real geometry (issue 18): work per pixel and CPU time of the per-pixel SPS sampler.

    python -m benchmarks.real_scenes         # once: generates and caches the scenes (a few minutes, one core)
    python -m benchmarks.sampler_real        # the table (a few minutes, one core)
    python -m benchmarks.sampler_real --quick --scenes lego_hull --configs 40:0.01

Scenes (:mod:`benchmarks.real_scenes`): ``default_fit`` (neural task, stage-1 surfels, 64²), ``lego_hull`` and
``lego_fit`` (lego visual-hull surfels, and after a short stage-1 fit, 200²), ``bunny`` (reconstruction
task's bunny, 256²) and ``random_20k`` (benchmarks/op_cpu.py's sphere scene, N = 20k, 128²). One camera each.

Per scene and (m, ε), over the pixels with coverage (dense Λ(x) > 1e-10):
  * sampler CPU time (``nsplat.ops.sample``, one thread, minimum of ``--repeats`` warm calls, process time),
  * exact kernel evaluations and tree nodes visited per pixel (the op's driver, run by a probe build),
  * λ support: points with λ > 1e-2 / 1e-3 / 1e-4 and inside 3σ (Mahalanobis ≤ 3) per pixel,
  * ``oracle``: the evaluations of a search with exact per-point bounds in decreasing λ order, i.e. the
    fewest points whose exact mass leaves a tail T with T·ξ_(m+1) < ε (the pruning rule's own minimum),
  * the inner loop alone (``offer_bench`` of the probe: ns per ``offer_point`` — one exact kernel evaluation with
    its draw, rejection test and heap update — over the points with λ > 1e-5 at 400 covered pixels, m = the row's),
  * op forward+backward CPU time (``splat``, one thread) and that of the 3σ-truncated tile rasteriser
    (``nsplat.truncated.splat_truncated``, autograd) on the same splats.
Support statistics use ``--stat-pixels`` random covered pixels. Writes benchmarks/results/sampler_real.json.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import REPO as ROOT
from benchmarks.common import RESULTS, machine
from benchmarks.op_cpu import scene as sphere_scene
from benchmarks.real_scenes import CACHE
SCENES = ("default_fit", "lego_hull", "lego_fit", "lego20k_hull", "bunny", "random_20k")
NEAR, FAR, LOWPASS = 0.01, 1e10, 1.0


def load_scene(name: str) -> dict:
    if name == "random_20k":
        params, V, K = sphere_scene(20000, 128)
        means, normals, scales, opac, _ = params
        return dict(means=means, normals=normals, scales=scales, opacities=opac, viewmat=V[0], K=K[0],
                    width=128, height=128)
    path = CACHE / f"{name}.pt"
    if not path.is_file():
        raise SystemExit(f"{path} missing: run python -m benchmarks.real_scenes first")
    return torch.load(path)


def probe_module():
    from torch.utils.cpp_extension import load

    from nsplat.ops.build import build_dir, source_hash

    src = ROOT / "benchmarks" / "native" / "sampler_probe.cpp"
    d = build_dir("probe")
    return load(name="nsplat_sampler_probe", sources=[str(src), str(ROOT / "ops/csrc/cpu/scatter_cpu.cpp")],
                extra_cflags=["-O3", "-fopenmp", "-std=c++17", f"-DNSPLAT_SOURCE_HASH={source_hash()}"],
                extra_ldflags=["-fopenmp"], build_directory=str(d), verbose=False)


def project_scene(sc: dict):
    from nsplat.ops import project

    return project(sc["means"].float(), sc["normals"].float(), sc["scales"].float(), sc["opacities"].float(),
                   sc["viewmat"][None].float(), sc["K"][None].float(), near=NEAR, far=FAR, lowpass=LOWPASS)


def cpu_min(fn, repeats: int) -> float:
    fn()  # warm
    best = math.inf
    for _ in range(repeats):
        c0 = time.process_time()
        fn()
        best = min(best, time.process_time() - c0)
    return best


def support_stats(proj, W: int, H: int, configs: list[tuple[int, float]], pixels: int, seed: int = 0) -> dict:
    """λ support counts and the oracle's evaluations on ``pixels`` random covered pixels (float64)."""
    from nsplat.ops.rng import uniforms

    mu = proj.means2d[0].double()
    con = proj.conics[0].double()
    amp = proj.amps[0].double() * proj.valid[0].double()
    keep = torch.nonzero(amp > 0).flatten()
    mu, con, amp = mu[keep], con[keep], amp[keep]
    g = torch.Generator().manual_seed(seed)
    cand = torch.randperm(W * H, generator=g)
    rows, pix_ids = [], []
    for chunk in cand.split(256):
        u = (chunk % W).double() + 0.5
        v = torch.div(chunk, W, rounding_mode="floor").double() + 0.5
        dx, dy = u[:, None] - mu[None, :, 0], v[:, None] - mu[None, :, 1]
        q = con[None, :, 0] * dx * dx + 2 * con[None, :, 1] * dx * dy + con[None, :, 2] * dy * dy
        lam = (amp[None] * torch.exp(-0.5 * q)).clamp(max=0.99)
        ok = lam.sum(1) > 1e-10
        rows.append((lam[ok], q[ok]))
        pix_ids.append(chunk[ok])
        if sum(r[0].shape[0] for r in rows) >= pixels:
            break
    lam = torch.cat([r[0] for r in rows])[:pixels]
    q = torch.cat([r[1] for r in rows])[:pixels]
    pid = torch.cat(pix_ids)[:pixels]
    out = {"pixels": int(lam.shape[0]), "lambda_total": float(lam.sum(1).mean())}
    for t in (1e-2, 1e-3, 1e-4):
        out[f"support_{t:g}"] = float((lam > t).sum(1).double().mean())
    out["support_3sigma"] = float(((q <= 9.0) & (lam > 0)).sum(1).double().mean())
    lam_np = lam.numpy()
    srt = -np.sort(-lam_np, axis=1)
    tail = np.cumsum(srt[:, ::-1], axis=1)[:, ::-1]  # tail[:, k] = sum_{j >= k} sorted lambda
    tail = np.concatenate([tail, np.zeros((tail.shape[0], 1))], axis=1)
    u = uniforms(1, 0, pid.numpy(), keep.numpy())
    with np.errstate(divide="ignore"):
        keys = np.where(lam_np > 0, np.log(u) - np.log(lam_np), np.inf)
    keys.sort(axis=1)
    for m, eps in configs:
        xi = np.exp(keys[:, m]) if keys.shape[1] > m else np.full(keys.shape[0], np.inf)
        need = np.array([np.argmax(tail[i] * xi[i] < eps) if np.isfinite(xi[i]) else int((lam_np[i] > 0).sum())
                         for i in range(tail.shape[0])])
        out[f"oracle_m{m}_eps{eps:g}"] = float(need.mean())
    return out


def op_times(sc: dict, m: int, eps: float, repeats: int) -> dict:
    from nsplat.ops import splat
    from nsplat.render_truncated import splat_truncated

    W, H = sc["width"], sc["height"]
    N = sc["means"].shape[0]
    feat = torch.rand(N, 3, generator=torch.Generator().manual_seed(0))
    base = [sc["means"].float(), sc["normals"].float(), sc["scales"].float(), sc["opacities"].float(), feat]
    V, K = sc["viewmat"][None].float(), sc["K"][None].float()

    def run(fn):
        def f():
            ps = [t.clone().requires_grad_() for t in base]
            out = fn(ps)
            (out.image.sum() + out.alpha.sum()).backward()
        return f

    op = cpu_min(run(lambda ps: splat(*ps, V, K, W, H, samples=m, eps=eps, seed=1)), repeats)
    trunc = cpu_min(run(lambda ps: splat_truncated(*ps, V, K, W, H, cutoff=3.0)), max(1, repeats // 2))
    return {"op_fwd_bwd_s": op, "truncated_fwd_bwd_s": trunc}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--configs", nargs="*", default=["40:0.01", "40:0.1", "8:0.01", "8:0.1"],
                    help="m:eps pairs")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--stat-pixels", type=int, default=1500)
    ap.add_argument("--quick", action="store_true", help="no op/truncated timings, 400 stat pixels")
    ap.add_argument("--out", default=str(RESULTS / "sampler_real.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from nsplat.ops import sample

    configs = [(int(c.split(":")[0]), float(c.split(":")[1])) for c in args.configs]
    probe = probe_module()
    rows = []
    for name in args.scenes:
        sc = load_scene(name)
        W, H = sc["width"], sc["height"]
        proj = project_scene(sc)
        stats = support_stats(proj, W, H, configs, 400 if args.quick else args.stat_pixels)
        for m, eps in configs:
            K = sc["K"][None].float()
            t = cpu_min(lambda: sample(proj, K, W, H, samples=m, eps=eps, seed=1), args.repeats)
            mu, con, amp, nrm, off, zc = (x.contiguous() for x in (proj.means2d, proj.conics, proj.amps,
                                                                    proj.normals_cam, proj.plane_offsets, proj.depths))
            _, _, total, work, nodes = probe.probe(mu, con, amp, proj.sigma2.contiguous(), nrm, off, zc, K, W, H, m,
                                                   eps, 1, 8, 1e-3)
            cov = total.flatten() > 0
            row = {"scene": name, "N": int(sc["means"].shape[0]), "res": f"{W}x{H}", "m": m, "eps": eps,
                   "sampler_s": t, "covered_pixels": int(cov.sum()),
                   "us_per_pixel": 1e6 * t / max(1, int(cov.sum())),
                   "evals_per_pixel": float(work.flatten()[cov].double().mean()),
                   "nodes_per_pixel": float(nodes.flatten()[cov].double().mean()),
                   "oracle_evals": stats[f"oracle_m{m}_eps{eps:g}"],
                   **{k: v for k, v in stats.items() if not k.startswith("oracle")},
                   "load": os.getloadavg()[0]}
            row["ns_per_eval"] = 1e9 * t / max(1.0, float(work.double().sum()))
            pix = torch.nonzero(cov).flatten()
            pix = pix[torch.randperm(pix.numel(), generator=torch.Generator().manual_seed(0))[:400]].contiguous()
            secs, offers = probe.offer_bench(mu, con, amp, proj.sigma2.contiguous(), pix, W, m, 1, 1e-5, args.repeats)
            row["inner_ns_per_eval"] = 1e9 * secs / max(1.0, offers)
            if not args.quick and (m, eps) == (40, 0.01):
                row.update(op_times(sc, m, eps, args.repeats))
            rows.append(row)
            print(json.dumps(row), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    meta = {"machine": machine(), "threads": 1,
            "command": "python -m benchmarks.sampler_real " + " ".join(sys.argv[1:]), "torch": torch.__version__}
    Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(table(rows))


def table(rows: list[dict]) -> str:
    head = ("| scene | N | res | m | ε | sampler s | µs/px | evals/px | nodes/px | oracle | λ>1e-2/1e-3/1e-4 | 3σ "
            "| evals/(λ>1e-3) | ns/eval | inner ns/eval | op f+b s | 3σ raster f+b s | load |")
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        out.append(
            f"| {r['scene']} | {r['N']} | {r['res']} | {r['m']} | {r['eps']:g} | {r['sampler_s']:.3f} | "
            f"{r['us_per_pixel']:.1f} | {r['evals_per_pixel']:.0f} | {r['nodes_per_pixel']:.0f} | "
            f"{r['oracle_evals']:.0f} | {r['support_0.01']:.0f}/{r['support_0.001']:.0f}/{r['support_0.0001']:.0f} | "
            f"{r['support_3sigma']:.0f} | {r['evals_per_pixel'] / max(r['support_0.001'], 1e-9):.1f} | "
            f"{r['ns_per_eval']:.0f} | {r.get('inner_ns_per_eval', float('nan')):.0f} | "
            f"{r.get('op_fwd_bwd_s', float('nan')):.2f} | "
            f"{r.get('truncated_fwd_bwd_s', float('nan')):.2f} | {r['load']:.1f} |")
    return "\n".join(out)


if __name__ == "__main__":
    main()
