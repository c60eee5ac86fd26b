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


def setup(config: str, ply: str):
    """``(cfg, train, val, load, start)``: the config, its train and val views, a loader of fresh copies of the
    surfels in ``ply`` and their val PSNR (printed)."""
    from nsplat.config import load_config, read_yaml
    from nsplat.scene import SurfelScene
    from nsplat.tasks.neural import load_views
    from nsplat.tasks.neural_config import Config
    from nsplat.tasks.neural_init import geometry_scene_config

    cfg = load_config(Config, read_yaml(config), [])
    cpu = torch.device("cpu")
    train, val = load_views(cfg, "train", cpu), load_views(cfg, "val", cpu)
    scene_cfg = geometry_scene_config(cfg)

    def load():
        return SurfelScene.load_ply(ply, scene_cfg, device=cpu)

    start = val_psnr(load(), cfg, val)
    print(f"{ply}: val PSNR {start:.2f} dB ({len(val)} views, {cfg.eval.draws} draws)")
    return cfg, train, val, load, start


def continue_fit(scene, train, fit_cfg, render_cfg, seed: int) -> tuple[dict[str, float], float, float]:
    """Fit ``scene`` further with ``fit_cfg`` (checkpoints discarded): the last step's scalars, wall and CPU s."""
    from nsplat.engine import LogConfig
    from nsplat.fitting import fit

    t0, c0 = time.perf_counter(), time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        out = fit(scene, train, fit_cfg, render_cfg, tmp, seed=seed, background=train.background,
                  log=LogConfig(checkpoint=10 ** 9, progress=False))
    return out, time.perf_counter() - t0, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", help="fitted surfels (a neural run's geometry.ply)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--factors", type=float, nargs="+", default=[0.25, 0.0625, 0.015625],
                    help="constant rate factors on the config's base rates")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()

    cfg, train, val, load, start = setup(args.config, args.ply)
    rows = []
    print("| rate factor | epochs | val PSNR | Δ | last-step loss | fit s (wall) |\n|---|---|---|---|---|---|")
    g = cfg.geometry.optim
    for f in args.factors:
        scene = load()
        ocfg = dataclasses.replace(g, epochs=args.epochs, lr_decays=0, anneal_epochs=0,
                                   learn={k: v * f for k, v in g.learn.items()})
        out, seconds, _ = continue_fit(scene, train, ocfg, cfg.render, args.seed)
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
