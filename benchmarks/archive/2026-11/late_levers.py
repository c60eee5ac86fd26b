"""What does a change to the stage-1 fit buy once the surfels have settled? (issue 28, session 8.)

Loads fitted surfels (a run's ``geometry.ply``, by default the annealed 72-epoch lego stage 1) and continues
the stage-1 fit of the config for ``--epochs`` epochs: the first at 1/4 of the base rates (the rate the run
left its high-rate phase at), the others annealed geometrically to 1/16 of that (a second tail, as
``geometry.optim.anneal_epochs``), fresh Adam, fit seed 7. Each variant changes one thing:

* ``control``: nothing (how much the second tail alone moves val);
* ``split30`` / ``clone30``: one density-control event after the first epoch (:mod:`nsplat.densify`) that
  splits (``split_size: 0``) or clones (``split_size: 1``) the 30 % of surfels with the largest average
  screen-space gradient, new rows with zero Adam moments (3DGS); ``split30i``: the same split with the
  moments inherited from the source rows (``densify.moments: inherit``);
* ``ssim``: 0.8·L1 + 0.2·D-SSIM (``geometry.optim.ssim_weight: 0.2``, 3DGS's image loss) instead of L1.

Reports the val PSNR (every val view, the evaluation's draws) after each continuation, the point count, the
last step's loss and the fit's wall and CPU seconds.

    python benchmarks/late_levers.py runs/ttq/lego/point-72ep-norepo-cap05-a12-s0/geometry.ply

Prints a table and writes ``benchmarks/results/late_levers.json``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from rate_floor import continue_fit, setup, val_psnr


def variants() -> dict[str, dict]:
    """FitConfig overrides per variant (``densify`` as a :class:`~nsplat.densify.DensifyConfig`)."""
    from nsplat.densify import DensifyConfig

    def event(growth: float, split_size: float, moments: str = "reset") -> DensifyConfig:
        return DensifyConfig(enabled=True, start=1, stop=1, grad_threshold=0.0, split_size=split_size,
                             max_growth=growth, max_points=10 ** 6, prune_opacity=0.02, moments=moments)

    return {"control": {}, "split30": {"densify": event(0.3, 0.0)}, "clone30": {"densify": event(0.3, 1.0)},
            "split30i": {"densify": event(0.3, 0.0, "inherit")}, "ssim": {"ssim_weight": 0.2}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ply", nargs="?", default=str(ROOT / "runs/ttq/lego/point-72ep-norepo-cap05-a12-s0/geometry.ply"),
                    help="fitted surfels (a run's geometry.ply)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "lego.yaml"))
    ap.add_argument("--variants", nargs="+", default=list(variants()), choices=list(variants()))
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()

    cfg, train, val, load, start = setup(args.config, args.ply)
    g = cfg.geometry.optim
    print("| variant | points | val PSNR | Δ | last-step loss | fit s (wall / CPU) |\n|---|---|---|---|---|---|")
    rows = []
    for name in args.variants:
        scene = load()
        ocfg = dataclasses.replace(g, epochs=args.epochs, lr_decays=0, anneal_epochs=args.epochs - 1,
                                   anneal_factor=1 / 16, learn={k: v * 0.25 for k, v in g.learn.items()},
                                   **variants()[name])
        out, wall, cpu_s = continue_fit(scene, train, ocfg, cfg.render, args.seed)
        v = val_psnr(scene, cfg, val)
        rows.append({"variant": name, "points": scene.num_points, "val_psnr": v, "loss": out["train/loss"],
                     "fit_s": wall, "cpu_s": cpu_s})
        print(f"| {name} | {scene.num_points} | {v:.2f} | {v - start:+.2f} | {out['train/loss']:.5f} | "
              f"{wall:.0f} / {cpu_s:.0f} |", flush=True)
    res = ROOT / "benchmarks" / "results" / "late_levers.json"
    res.write_text(json.dumps({"ply": args.ply, "config": args.config, "epochs": args.epochs, "val_views": len(val),
                               "start_val_psnr": start, "threads": torch.get_num_threads(), "load": os.getloadavg(),
                               "rows": rows}, indent=1))
    print(f"written {res}")


if __name__ == "__main__":
    main()
