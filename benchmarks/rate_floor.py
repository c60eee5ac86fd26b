"""Is a fitted stage 1 limited by its last learning rate? (issue 28, session 7: the annealing tail.)

Loads fitted surfels (a run's ``geometry.ply``), continues the stage-1 fit of the config (``configs/lego.yaml``
by default) for ``--epochs`` epochs at constant rates — each ``--factors`` value times the config's base rates
(fresh Adam, no halvings) — and reports the validation PSNR of the val split (every view, the evaluation's
draws) before and after each continuation, with the last step's training loss and the fit's wall time. If
continuing at the run's own final factor (1/4 of the base after the 2 halvings) changes nothing while a lower
factor gains, the surfels were jittering at the scale of the rate: an annealing tail
(``geometry.optim.anneal_epochs``) buys that gain inside the same number of epochs.

    python benchmarks/rate_floor.py runs/ttq/lego/point-72ep-norepo-cap05-s0/geometry.ply \\
        --factors 0.25 0.0625 0.015625 --epochs 6

Prints a table and writes ``benchmarks/results/rate_floor.json``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def val_psnr(scene, cfg, val) -> float:
    """Mean PSNR of ``scene`` on every view of ``val`` (evaluation render settings and draws)."""
    from nsplat.metrics_image import psnr
    from nsplat.render import render_views

    with torch.no_grad():
        rgb = torch.cat([render_views(scene, val.viewmats[s:s + 4], val.Ks[s:s + 4], val.width, val.height,
                                      cfg.eval_render(), seed=1000 + s, shading=cfg.geometry.optim.shading,
                                      background=val.background, draws=cfg.eval.draws)
                         for s in range(0, len(val), 4)]).clamp(0, 1)
    return float(psnr(rgb, val.images).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", help="fitted surfels (a neural run's geometry.ply)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--factors", type=float, nargs="+", default=[0.25, 0.0625, 0.015625],
                    help="constant rate factors on the config's base rates")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()

    from nsplat.config import load_config, read_yaml
    from nsplat.engine import LogConfig
    from nsplat.fitting import fit
    from nsplat.scene import SurfelScene
    from nsplat.tasks.neural import load_views
    from nsplat.tasks.neural_config import Config
    from nsplat.tasks.neural_init import geometry_scene_config

    cfg = load_config(Config, read_yaml(args.config), [])
    cpu = torch.device("cpu")
    train, val = load_views(cfg, "train", cpu), load_views(cfg, "val", cpu)
    scene_cfg = geometry_scene_config(cfg)
    start = val_psnr(SurfelScene.load_ply(args.ply, scene_cfg, device=cpu), cfg, val)
    rows = []
    print(f"{args.ply}: val PSNR {start:.2f} dB ({len(val)} views, {cfg.eval.draws} draws)")
    print("| rate factor | epochs | val PSNR | Δ | last-step loss | fit s (wall) |\n|---|---|---|---|---|---|")
    g = cfg.geometry.optim
    for f in args.factors:
        scene = SurfelScene.load_ply(args.ply, scene_cfg, device=cpu)
        ocfg = dataclasses.replace(g, epochs=args.epochs, lr_decays=0, anneal_epochs=0,
                                   learn={k: v * f for k, v in g.learn.items()})
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            out = fit(scene, train, ocfg, cfg.render, tmp, seed=args.seed, background=train.background,
                      log=LogConfig(checkpoint=10 ** 9, progress=False))
        seconds = time.perf_counter() - t0
        v = val_psnr(scene, cfg, val)
        rows.append({"factor": f, "epochs": args.epochs, "val_psnr": v, "loss": out["train/loss"], "fit_s": seconds})
        print(f"| {f:g} | {args.epochs} | {v:.2f} | {v - start:+.2f} | {out['train/loss']:.5f} | {seconds:.0f} |",
              flush=True)
    res = ROOT / "benchmarks" / "results" / "rate_floor.json"
    res.write_text(json.dumps({"ply": args.ply, "config": args.config, "val_views": len(val), "start_val_psnr": start,
                               "threads": torch.get_num_threads(), "load": os.getloadavg(), "rows": rows}, indent=1))
    print(f"written {res}")


if __name__ == "__main__":
    main()
