"""Score finished reconstruction runs on held-out images at one common resolution: the yardstick that selects the
reconstruction recipe (``docs/results.md``, "Shape reconstruction") across runs trained at different resolutions.

A run's own ``heldout_psnr`` is measured at its training resolution, so a 128² run and a 256² run are not
comparable on it. This script renders each run's last checkpoint on the task's held-out views at ``--size``
(:func:`nsplat.tasks.reconstruct.render_heldout`, the GT renderer for both sides) and reports the PSNR beside the
run's own metrics. The GT point cloud's distances are copied for the docs, never used to select.

    python -m benchmarks.reconstruct_select RUN_DIR [RUN_DIR ...] --size 256 [--name NAME]

Writes ``benchmarks/results/reconstruct_select-<name>.json`` (rows: run, command, shape, training resolution,
epochs, held-out PSNR at ``--size``, Chamfer/Hausdorff, wall and CPU seconds) and prints the table.
"""
from __future__ import annotations

import argparse
import json
import types
from pathlib import Path

import torch

from benchmarks.common import markdown, write_result
from nsplat.config import load_config, read_yaml
from nsplat.data.pointclouds import load_shape
from nsplat.evaluation.image_metrics import psnr
from nsplat.tasks import reconstruct


def score(run_dir: Path, size: int) -> dict:
    """The run's metrics plus ``heldout_psnr_at`` (its last checkpoint on the held-out views at ``size``²)."""
    raw = read_yaml(run_dir / "config.yaml")
    cfg = load_config(reconstruct.Config, raw, [f"data.width={size}", f"data.height={size}"])
    pc = load_shape(cfg.data.shape, cfg.data.root or None)
    scene = reconstruct.restore(cfg, types.SimpleNamespace(run_dir=run_dir, device=torch.device("cpu")))
    held, rec = reconstruct.render_heldout(cfg, pc, scene)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    return {"run": run_dir.name, "shape": metrics["shape"], "trained_at": metrics["resolution"],
            "epochs": metrics["epochs"], "heldout_psnr_at": float(psnr(rec.clamp(0, 1), held.images).mean()),
            "heldout_psnr_own": metrics["heldout_psnr"], "chamfer": metrics["chamfer"],
            "hausdorff": metrics["hausdorff"], "init_chamfer": metrics["init"]["chamfer"],
            "fit_seconds": metrics["fit_seconds"], "cpu_seconds": metrics["cpu_seconds"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="finished reconstruct run folders")
    p.add_argument("--size", type=int, default=256, help="held-out image side (pixels) every run is scored at")
    p.add_argument("--name", default="256", help="suffix of the JSON file")
    p.add_argument("--commands", type=Path, default=None,
                   help="optional JSON mapping run folder name -> the command that made it")
    args = p.parse_args()
    commands = json.loads(args.commands.read_text()) if args.commands else {}
    rows = []
    for run in args.runs:
        row = score(run, args.size)
        row["command"] = commands.get(run.name, "")
        rows.append(row)
    table = markdown(["run", "shape", "trained at", "epochs", f"held-out PSNR at {args.size}²", "own PSNR", "Chamfer",
                      "Hausdorff", "wall s"],
                     [[r["run"], r["shape"], f"{r['trained_at'][0]}²", r["epochs"], f"{r['heldout_psnr_at']:.2f}",
                       f"{r['heldout_psnr_own']:.2f}", f"{r['chamfer']:.4f}", f"{r['hausdorff']:.4f}",
                       f"{r['fit_seconds']:.0f}"] for r in rows])
    write_result(f"reconstruct_select-{args.name}", {"size": args.size, "rows": rows}, table)


if __name__ == "__main__":
    main()
