"""Bias and variance of every gradient estimator against the dense gradient, vs samples per pixel.

For each scene (a random skewed-size scene and the DSS bunny as surfels), compositing mode (additive,
alpha), sample size m and estimator (``sampled``, ``paper``, ``ht-pips``, ``ht``, ``ht`` with stratified
draws), it draws ``groups × per_group`` sampled gradients of a fixed linear loss ``Σ w·image`` in float64
(:func:`nsplat.ops.diagnostics.estimator_study`) and reports

- ``bias_proj``: the bias along the dense gradient, relative (0.01 = the whole gradient 1 % too large),
  with its standard error and the ratio ``bias_z`` = bias / SE;
- ``z2``: the mean squared standardised error over all parameter entries (≈ 1.05 for an unbiased
  estimator at any number of draws; grows with the draws under any bias);
- ``cos_mean``: cosine between the mean sampled gradient and the dense one (direction bias);
- ``rel_std``: the standard deviation of one single-camera gradient relative to the dense gradient (RMS);
- ``rel_rmse``: root-mean-square error of one single-camera gradient, ``sqrt(bias² + var)``, relative;
- ``ms_per_draw``: sampled forward + backward time per camera (one thread; indicative only).

Usage::

    python -m benchmarks.estimators                      # full table -> benchmarks/results/estimators.json
    python -m benchmarks.estimators --quick              # fewer draws, for a smoke run
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

from benchmarks.common import IMAGES, write_result
from nsplat.cameras import look_at
from nsplat.data.pointclouds import load_dss_shape
from nsplat.ops.diagnostics import estimator_study

VARIANTS = (("sampled", False), ("paper", False), ("ht-pips", False), ("ht", False), ("ht", True))


def random_scene(N: int = 150, seed: int = 4) -> dict[str, torch.Tensor]:
    """Surfels in a cube facing the camera, sizes log-uniform over a factor 12 (skewed λ per pixel)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    means = (torch.rand(N, 3, generator=g, dtype=d) - 0.5) * 0.8
    normals = torch.randn(N, 3, generator=g, dtype=d) * 0.5
    normals[:, 2] = -normals[:, 2].abs() - 0.5
    lo, hi = math.log(0.015), math.log(0.18)
    s = torch.exp(lo + (hi - lo) * torch.rand(N, generator=g, dtype=d))
    scales = torch.stack([s, s * (0.6 + 0.4 * torch.rand(N, generator=g, dtype=d))], 1)
    opacities = 0.3 + 0.6 * torch.rand(N, generator=g, dtype=d)
    features = torch.rand(N, 3, generator=g, dtype=d)
    return dict(means=means, normals=normals, scales=scales, opacities=opacities, features=features)


def bunny_scene(N: int = 1500, seed: int = 0) -> dict[str, torch.Tensor]:
    """``N`` points of the DSS bunny (unit radius, centred) as opaque surfels sized to the point spacing,
    coloured by their normals."""
    pc = load_dss_shape("bunny", dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    pick = torch.randperm(pc.points.shape[0], generator=g)[:N]
    pts = (pc.points[pick] - pc.center) / pc.radius
    nrm = torch.nn.functional.normalize(pc.normals[pick], dim=-1)
    spacing = math.sqrt(4.0 / N)
    return dict(means=pts, normals=nrm, scales=torch.full((N, 2), 0.6 * spacing, dtype=torch.float64),
                opacities=torch.full((N,), 0.8, dtype=torch.float64), features=0.5 + 0.5 * nrm)


def camera(kind: str, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``([1,4,4], [1,3,3])`` for the scene kind at ``size``² pixels."""
    d = torch.float64
    if kind == "random":
        V = torch.eye(4, dtype=d)[None]
        V[0, 2, 3] = 2.5
        f = 1.1 * size
    else:
        V = look_at(torch.tensor([[1.6, 0.9, 2.0]], dtype=d), torch.zeros(1, 3, dtype=d),
                    torch.tensor([0.0, 1.0, 0.0], dtype=d))
        f = 1.25 * size
    K = torch.tensor([[[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]]], dtype=d)
    return V, K


def run(args: argparse.Namespace) -> list[dict]:
    rows = []
    torch.set_num_threads(1)
    for kind in args.scenes:
        sc = random_scene() if kind == "random" else bunny_scene()
        size = 24 if kind == "random" else 32
        V, K = camera(kind, size)
        w = torch.randn(size, size, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
        for composite in args.composites:
            for m in args.ms:
                for estimator, stratified in VARIANTS:
                    t0 = time.process_time()
                    st = estimator_study(sc, V, K, size, size, w, estimator=estimator, samples=m,
                                         composite=composite, groups=args.groups, per_group=args.per_group,
                                         stratified=stratified)
                    cpu = time.process_time() - t0
                    b, bse = st.projected_bias()
                    z = st.z()
                    bias2 = max(float(((st.mean - st.dense) ** 2).sum() - (st.se ** 2).sum()), 0.0)
                    rmse = math.sqrt(bias2 + float((st.std ** 2).sum())) / float(st.dense.norm())
                    row = dict(scene=kind, N=int(sc["means"].shape[0]), size=size, composite=composite, m=m,
                               estimator=estimator + ("+strat" if stratified else ""), draws=st.draws,
                               bias_proj=b, bias_se=bse, bias_z=b / bse if bse > 0 else 0.0,
                               z2=float((z ** 2).mean()), cos_mean=st.cosine(), rel_std=st.relative_std(),
                               rel_rmse=rmse,
                               ms_per_draw=1e3 * cpu / st.draws)
                    rows.append(row)
                    print(f"{kind:6s} {composite:8s} m={m:<3d} {row['estimator']:12s} "
                          f"bias {b:+.4f}±{bse:.4f} ({row['bias_z']:+6.1f} SE)  z²={row['z2']:7.2f}  "
                          f"cos {row['cos_mean']:.3f}  "
                          f"std {row['rel_std']:.3f}  rmse {rmse:.3f}  {row['ms_per_draw']:.2f} ms/draw", flush=True)
    return rows


def markdown(rows: list[dict]) -> str:
    """The table of docs/results.md "Gradient estimators"."""
    lines = ["| scene | compositing | m | estimator | bias along ∇ (rel.) | in SE | mean z² | cos(E[g], ∇) | "
             "rel. std / draw | rel. RMSE / draw |", "|---|---|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['composite']} | {r['m']} | {r['estimator']} | {r['bias_proj']:+.4f} | "
                     f"{r['bias_z']:+.1f} | {r['z2']:.3g} | {r.get('cos_mean', float('nan')):.3f} | "
                     f"{r['rel_std']:.3f} | {r['rel_rmse']:.3f} |")
    return "\n".join(lines)


def plot(rows: list[dict], out: Path) -> None:
    """Relative single-draw RMSE and |bias| in SE vs m, one panel per scene × compositing."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = sorted({(r["scene"], r["composite"]) for r in rows})
    fig, axes = plt.subplots(2, len(keys), figsize=(4 * len(keys), 6.5), squeeze=False)
    for j, key in enumerate(keys):
        sub = [r for r in rows if (r["scene"], r["composite"]) == key]
        for est in dict.fromkeys(r["estimator"] for r in sub):
            pts = sorted((r["m"], r["rel_rmse"], abs(r["bias_z"])) for r in sub if r["estimator"] == est)
            ms = [p[0] for p in pts]
            axes[0, j].plot(ms, [p[1] for p in pts], marker="o", label=est)
            axes[1, j].plot(ms, [max(p[2], 1e-2) for p in pts], marker="o", label=est)
        axes[0, j].set(title=f"{key[0]}, {key[1]}", xscale="log", yscale="log", xlabel="m",
                       ylabel="relative RMSE of one draw")
        axes[1, j].axhline(3.0, color="grey", lw=0.8, ls="--")
        axes[1, j].set(xscale="log", yscale="log", xlabel="m", ylabel="|bias along gradient| / SE")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["random", "bunny"], choices=["random", "bunny"])
    p.add_argument("--composites", nargs="+", default=["additive", "alpha"], choices=["additive", "alpha"])
    p.add_argument("--ms", nargs="+", type=int, default=[1, 4, 16, 40])
    p.add_argument("--groups", type=int, default=40)
    p.add_argument("--per-group", type=int, default=50)
    p.add_argument("--quick", action="store_true", help="10 draws per group (smoke run)")
    p.add_argument("--name", default="estimators")
    args = p.parse_args()
    if args.quick:
        args.per_group = 10
    t0 = time.time()
    rows = run(args)
    meta = dict(command="python -m benchmarks.estimators " + " ".join(sys.argv[1:]), wall_s=time.time() - t0)
    write_result(args.name, dict(meta=meta, rows=rows, markdown=markdown(rows)))
    plot(rows, IMAGES / "estimators" / f"{args.name}.png")


if __name__ == "__main__":
    main()
