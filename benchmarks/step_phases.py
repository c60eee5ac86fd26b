"""Where the time of one stage-1 step goes.

Loads fitted surfels (default: ``runs/lego_splat_only/geometry.ply``, configs/lego_splat_only.yaml's stage 1) and runs
the stage-1 step of the config
phase by phase on the training views, one view per step as the fitter does: view-dependent colour
(:func:`nsplat.render.sh.view_colour`), projection, the sampler, compositing, the L1 loss, the backward of all of
them, and the Adam step. Reports the mean wall milliseconds of each phase over ``--steps`` steps (after 3
warm-up steps) and its share.

    python train.py --config configs/lego_splat_only.yaml --run runs/lego_splat_only   # the surfels (30 min)
    python -m benchmarks.step_phases runs/lego_splat_only/geometry.ply

Prints a table and writes ``benchmarks/results/step_phases.json``.
"""
from __future__ import annotations

import argparse
import sys
import time

import torch

from benchmarks.common import REPO as ROOT
from benchmarks.common import write_result
from nsplat.config import load_config, read_yaml
from nsplat.ops import composite_sample, project, sample
from nsplat.ops.validation import inclusion_for
from nsplat.render.sh import view_colour
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.starts import geometry_scene_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", nargs="?", default=str(ROOT / "runs" / "lego_splat_only" / "geometry.ply"))
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    cfg = load_config(Config, read_yaml(args.config), [])
    if cfg.geometry.optim.shading != "sh":
        raise SystemExit(f"{args.config}: this benchmark times the SH stage 1 (geometry.optim.shading: sh)")
    views = load_views(cfg, "train", torch.device("cpu"))
    scene = SurfelScene.load_ply(args.ply, geometry_scene_config(cfg), device=torch.device("cpu"))
    opt = torch.optim.Adam([p for p in scene.parameters() if p.requires_grad], lr=1e-6, fused=True)  # as the fitter
    r, w, h = cfg.render, views.width, views.height
    phases = ("view colour", "projection", "sampler", "compositing", "loss", "backward", "Adam step")
    total = dict.fromkeys(phases, 0.0)

    def timed(name: str, fn):
        t0 = time.perf_counter()
        out = fn()
        total[name] += time.perf_counter() - t0
        return out

    for it in range(args.steps + 3):
        if it == 3:
            total = dict.fromkeys(phases, 0.0)
        v = it % len(views)
        vm, K = views.viewmats[v:v + 1], views.Ks[v:v + 1]
        opt.zero_grad(set_to_none=True)
        feats = timed("view colour", lambda: view_colour(scene.features, scene.means, vm[0]))
        proj = timed("projection", lambda: project(scene.means, scene.normals, scene.scales, scene.opacities, vm, K,
                                                   near=r.near, far=r.far, lowpass=r.lowpass,
                                                   backface_cull=r.backface_cull))
        idx, probs, _, _ = timed("sampler", lambda: sample(
            proj, K, w, h, samples=r.samples, eps=r.eps, seed=it, hermite_order=r.hermite_order,
            hermite_tol=r.hermite_tol, inclusion=inclusion_for(r.estimator)))
        img, _, _ = timed("compositing", lambda: composite_sample(
            proj, feats, K, idx, probs, background=views.background, composite=r.composite, estimator=r.estimator,
            deterministic=r.deterministic))
        loss = timed("loss", lambda: (img - views.images[v:v + 1]).abs().mean())
        timed("backward", loss.backward)
        timed("Adam step", opt.step)
    step = sum(total.values())
    rows = [{"phase": k, "ms": 1000 * t / args.steps, "share": t / step} for k, t in total.items()]
    print(f"{args.ply}: {scene.num_points} surfels, {w}x{h}, m = {r.samples}, {torch.get_num_threads()} threads")
    print("| phase | ms per step | share |\n|---|---|---|")
    for row in rows:
        print(f"| {row['phase']} | {row['ms']:.1f} | {100 * row['share']:.0f} % |")
    print(f"| step | {1000 * step / args.steps:.1f} | |")
    write_result("step_phases", {"ply": args.ply, "config": args.config, "points": scene.num_points,
                                 "steps": args.steps, "rows": rows, "step_ms": 1000 * step / args.steps})


if __name__ == "__main__":
    sys.exit(main())
