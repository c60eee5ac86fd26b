"""Is a fitted stage 1 limited by its last learning rate? (what led to the annealing tail)

Loads fitted surfels (a run's ``geometry.ply``), continues the stage-1 fit of the config (``configs/lego.yaml``
by default) for ``--epochs`` epochs at constant rates — each ``--factors`` value times the config's base rates
(fresh Adam, no halvings) — and reports the validation PSNR of the val split (every view, the evaluation's
draws) before and after each continuation, with the last step's training loss and the fit's wall time. If
continuing at the run's own final factor (1/4 of the base after the 2 halvings) changes nothing while a lower
factor gains, the surfels were jittering at the scale of the rate: an annealing tail
(``geometry.optim.anneal_epochs``) buys that gain inside the same number of epochs.

    python train.py --config configs/lego_splat_only.yaml --run runs/lego_splat_only   # the surfels (30 min)
    python -m benchmarks.rate_floor runs/lego_splat_only/geometry.ply --factors 0.25 0.0625 0.015625 --epochs 6

Prints a table and writes ``benchmarks/results/rate_floor.json``.
"""
from __future__ import annotations

import argparse
import dataclasses

from benchmarks.common import REPO as ROOT
from benchmarks.common import write_result
from benchmarks.fitted import continue_fit, load_fitted, val_psnr


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", help="fitted surfels (a neural run's geometry.ply)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--factors", type=float, nargs="+", default=[0.25, 0.0625, 0.015625],
                    help="constant rate factors on the config's base rates")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()

    fitted = load_fitted(args.config, args.ply)
    cfg, train, val, load = fitted.cfg, fitted.train, fitted.val, fitted.load
    start = val_psnr(load(), cfg, val)
    print(f"{args.ply}: val PSNR {start:.2f} dB ({len(val)} views, {cfg.eval.draws} draws)")
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
    write_result("rate_floor", {"ply": args.ply, "config": args.config, "val_views": len(val),
                                "start_val_psnr": start, "rows": rows})


if __name__ == "__main__":
    main()
