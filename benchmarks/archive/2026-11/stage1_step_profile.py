"""Where a stage-1 step's time goes (issue 28): SH colour, projection, sampling, compositing, backward.

Loads fitted surfels (a run's ``geometry.ply``) and the training views of a neural config, then times
``--steps`` fitter-like steps (one view each: SH colour → ``nsplat.ops.project`` → ``sample`` →
``composite_sample`` → L1 → backward; no optimiser step, so every step sees the same surfels) after two
warm-up steps, at each ``--resolutions`` (the views downscaled like ``geometry.optim.coarse_epochs`` does).

    python benchmarks/stage1_step_profile.py runs/ttq/lego/point-42ep-norepo-s0/geometry.ply
    python benchmarks/stage1_step_profile.py PLY --config configs/lego.yaml --resolutions 200 100 --steps 10

Prints a table (ms per step and phase, wall; the process CPU seconds beside) and writes
``benchmarks/results/stage1_step_profile.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
PHASES = ("sh_colour", "project", "sample", "composite", "loss", "backward")


def profile(ply: str, config: str, resolution: int, steps: int) -> dict:
    from nsplat.config import load_config, read_yaml
    from nsplat.ops import composite_sample, project, sample
    from nsplat.ops.validation import inclusion_for
    from nsplat.scene import SurfelScene
    from nsplat.sh import view_colour
    from nsplat.tasks.neural import load_views
    from nsplat.tasks.neural_config import Config
    from nsplat.tasks.neural_init import geometry_scene_config

    cfg = load_config(Config, read_yaml(config), [])
    views = load_views(cfg, "train", torch.device("cpu"))
    views = views.downscaled(views.width // resolution)
    scene = SurfelScene.load_ply(ply, geometry_scene_config(cfg))
    bg, r = torch.tensor(cfg.data.background), cfg.render
    acc = dict.fromkeys(PHASES, 0.0)
    cpu0 = 0.0
    for k in range(steps + 2):
        if k == 2:
            acc, cpu0 = dict.fromkeys(PHASES, 0.0), time.process_time()
        v = k % len(views)
        t = [time.perf_counter()]
        f = view_colour(scene.features, scene.means, views.viewmats[v])
        t.append(time.perf_counter())
        proj = project(scene.means, scene.normals, scene.scales, scene.opacities, views.viewmats[v:v + 1],
                       views.Ks[v:v + 1], near=r.near, far=r.far, lowpass=r.lowpass)
        t.append(time.perf_counter())
        idx, probs, _, _ = sample(proj, views.Ks[v:v + 1], views.width, views.height, samples=r.samples, eps=r.eps,
                                  seed=k, inclusion=inclusion_for(r.estimator))
        t.append(time.perf_counter())
        img, _, _ = composite_sample(proj, f, views.Ks[v:v + 1], idx, probs, background=bg, estimator=r.estimator)
        t.append(time.perf_counter())
        loss = (img - views.images[v:v + 1]).abs().mean()
        t.append(time.perf_counter())
        loss.backward()
        t.append(time.perf_counter())
        for name, a, b in zip(PHASES, t, t[1:]):
            acc[name] += b - a
    ms = {name: 1000.0 * s / steps for name, s in acc.items()}
    return {"resolution": resolution, "points": scene.num_points, "ms": ms, "total_ms": sum(ms.values()),
            "cpu_ms": 1000.0 * (time.process_time() - cpu0) / steps}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", help="fitted surfels (a neural run's geometry.ply)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--resolutions", type=int, nargs="+", default=[200, 100])
    ap.add_argument("--steps", type=int, default=10)
    args = ap.parse_args()
    rows = [profile(args.ply, args.config, res, args.steps) for res in args.resolutions]
    print(f"| resolution | points | {' | '.join(PHASES)} | total ms | CPU ms |")
    print("|---" * (len(PHASES) + 4) + "|")
    for r in rows:
        print(f"| {r['resolution']}² | {r['points']} | " + " | ".join(f"{r['ms'][p]:.1f}" for p in PHASES)
              + f" | {r['total_ms']:.1f} | {r['cpu_ms']:.1f} |")
    out = ROOT / "benchmarks" / "results" / "stage1_step_profile.json"
    out.write_text(json.dumps({"meta": {"threads": torch.get_num_threads(), "load": os.getloadavg(),
                                        "machine": platform.processor() or platform.machine(), "ply": args.ply,
                                        "config": args.config, "steps": args.steps}, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
