"""Long run of the op's property tests (tests/test_op_properties.py) on many random small scenes.

Draws ``--scenes`` cases from the same generator as the hypothesis test (the documented input
domain of docs/op.md, edges included) with a numpy RNG, runs forward and backward, checks every
property and writes the count, timing and any failures (with the seed that reproduces each) to
``benchmarks/results/properties_soak.json``.

    OMP_NUM_THREADS=1 python -m tools.properties_soak --scenes 10000
    python -m tools.properties_soak --replay 1234      # re-run one failing scene verbosely

It also runs one-dimensional sweeps to the domain's edges (splat screen size × low-pass, world
offset, depth scale, opacity, focal length, culled points, image size) and stores, per value,
whether outputs and gradients are finite and the error against the float64 dense oracle.
"""
from __future__ import annotations

import argparse
import json
import os
import time
import traceback
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import RESULTS, machine
from tests.test_op_properties import Draw, check_case, describe, draw_case


# ---------------------------------------------------------------------------------------- domain edges
def _edge_scene(dtype, sigma_px=1.0, z=2.0, offset=0.0, opacity=0.8, focal=10.0, N=6):
    """``N`` splats facing a camera at the origin (f = ``focal`` px, 9×9 image) at depth ~z, with
    screen std-dev ``sigma_px`` (minor axis half of it); everything shifted by ``offset`` (world)."""
    g = torch.Generator().manual_seed(0)
    means = torch.zeros(N, 3, dtype=torch.float64)
    means[:, 2] = z
    means[:, :2] = (torch.rand(N, 2, generator=g, dtype=torch.float64) - 0.5) * 0.2 * z * 10.0 / focal
    normals = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(N, 3).clone()
    s = sigma_px * z / focal
    scales = torch.tensor([s, 0.5 * s], dtype=torch.float64).expand(N, 2).clone()
    opac = torch.full((N,), opacity, dtype=torch.float64)
    feats = torch.rand(N, 3, generator=g, dtype=torch.float64)
    V = torch.eye(4, dtype=torch.float64)[None].clone()
    V[0, :3, 3] = -offset
    means = means + offset
    K = torch.tensor([[[focal, 0.0, 4.5], [0.0, focal, 4.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    return [t.to(dtype) for t in (means, normals, scales, opac, feats, V, K)]


def _edge_check(ts, W=9, H=9, ref=None, **kw) -> dict:
    from nsplat.ops import splat, splat_dense
    leaves = [t.clone().requires_grad_() for t in ts[:6]]
    bg = torch.full((3,), 0.5, dtype=ts[0].dtype)
    try:
        out = splat(*leaves, ts[6], W, H, samples=8, background=bg, **kw)
    except (ValueError, TypeError) as exc:
        return {"error": f"{type(exc).__name__}: {exc}"}
    fin = all(bool(torch.isfinite(getattr(out, n)).all()) for n in ("image", "alpha", "depth", "total", "probs"))
    loss = out.image.square().sum() + out.alpha.sum() + out.depth.sum() / max(1.0, float(out.depth.abs().max()))
    grads = torch.autograd.grad(loss, leaves)
    bad = [n for n, gr in zip(("means", "normals", "scales", "opacities", "features", "viewmats"), grads)
           if not bool(torch.isfinite(gr).all())]
    if ref is None:
        d = [t.double() for t in ts]
        ref = splat_dense(*d, W, H, background=bg.double(),
                          **{k: v for k, v in kw.items() if k in ("lowpass", "near", "far")}).image
    err = float((out.image.detach().double() - ref).abs().max())
    return {"outputs_finite": fin, "grads_finite": not bad, "nonfinite_grads": bad, "max_err_vs_dense64": err}


def edge_sweeps() -> list[dict]:
    """One-dimensional sweeps to the edges of the input domain (docs/op.md "Valid input domain")."""
    rows = []
    dts = (torch.float32, torch.float64)

    def add(sweep, value, dtype, res, **extra):
        rows.append({"sweep": sweep, "value": value, "dtype": str(dtype).replace("torch.", ""), **extra, **res})

    for lp in (0.0, 1e-12, 1.0):
        for dt in dts:
            for k in range(-30, 31, 2):
                add("sigma_px", 10.0 ** k, dt, _edge_check(_edge_scene(dt, sigma_px=10.0 ** k), lowpass=lp),
                    lowpass=lp)
    base = _edge_check(_edge_scene(torch.float64))
    from nsplat.ops import splat_dense
    ref0 = splat_dense(*_edge_scene(torch.float64), 9, 9, background=torch.full((3,), 0.5, dtype=torch.float64)).image
    for dt in dts:
        for T in (0.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e12):
            add("offset", T, dt, _edge_check(_edge_scene(dt, offset=T), ref=ref0))
        for D in (1e-30, 1e-20, 1e-10, 1e-5, 1.0, 1e5, 1e10, 1e20, 1e30, 1e36, 1e38):
            add("depth_scale", D, dt, _edge_check(_edge_scene(dt, z=2.0 * D), ref=ref0, near=1e-2 * D * 2 if D < 1
                                                  else 0.01, far=1e300 if dt == torch.float64 else 3e38))
        for o in (0.0, 1e-40, 1e-30, 1e-12, 0.5, 1.0):
            add("opacity", o, dt, _edge_check(_edge_scene(dt, opacity=o)))
        for f in (1e-6, 1e-3, 1.0, 1e3, 1e6, 1e9):
            add("focal_px", f, dt, _edge_check(_edge_scene(dt, focal=f)))
        # a point culled beyond `far`: project() evaluates its discarded intermediates with z := 1, so
        # they grow like f·s·(1 + |x| + |y|) (camera coordinates); swept through s and through x
        for fs in (1e6, 1e9, 1e12, 1e15, 1e17, 1e18, 1e19, 1e20):
            ts = _edge_scene(dt)
            ts[0][0] = torch.tensor([0.0, 0.0, 2e10], dtype=dt)
            ts[2][0] = torch.tensor([fs / 10.0, fs / 20.0], dtype=dt)
            add("culled_f_s_lateral", fs, dt, _edge_check(ts), via="scale")
            ts = _edge_scene(dt)
            ts[0][0] = torch.tensor([fs / 10.0 - 1.0, 0.0, 2e10], dtype=dt)
            ts[1][0] = torch.tensor([0.6, 0.0, -0.8], dtype=dt)  # tilted: the tangent axes have a z part
            ts[2][0] = torch.tensor([1.0, 0.5], dtype=dt)
            add("culled_f_s_lateral", fs, dt, _edge_check(ts), via="lateral offset")
    for W, H in ((1, 1), (1, 4096), (4096, 1), (1024, 1024), (2048, 2048)):
        t0 = time.perf_counter()
        r = _edge_check(_edge_scene(torch.float32, N=50), W=W, H=H)
        add("image_size", f"{W}x{H}", torch.float32, r, seconds=round(time.perf_counter() - t0, 2))
    del base
    return rows


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
    p.add_argument("--no-edges", action="store_true", help="skip the one-dimensional domain-edge sweeps")
    p.add_argument("--out", type=Path, default=RESULTS / "properties_soak.json")
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
    edges = [] if args.no_edges else edge_sweeps()
    for r in edges:
        if not (r.get("outputs_finite", True) and r.get("grads_finite", True)) or "error" in r:
            print("edge:", r)
    result = {
        "scenes": args.scenes, "first_seed": args.first_seed, "max_points": args.max_points,
        "max_size": args.max_size, "failing_scenes": len(failures), "violations": dict(kinds),
        "failures": failures[:200], "wall_s": round(wall, 1), "process_time_s": round(cpu, 1),
        "threads": torch.get_num_threads(), "torch": torch.__version__,
        "draws": dict(sorted(stats.items())), "edges": edges, "machine": machine(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"{args.scenes} scenes, {len(failures)} failing ({dict(kinds)}); {wall:.0f}s wall, "
          f"{cpu:.0f}s CPU, {torch.get_num_threads()} thread(s) -> {args.out}")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
