"""Side-by-side summary of finished neural-task runs: a table, a JSON record and a figure.

For each ``label=run_folder`` it reads what a run of ``python train.py --config ...`` (task ``neural``) leaves
behind — ``history.json`` (train/val PSNR over stage-2 steps), ``eval_<split>/metrics.json`` and
``per_view.json`` (held-out metrics), ``eval_geometry.json`` (stage 1 alone), ``timing.json`` and the run's
``config.yaml`` — and writes

* ``benchmarks/results/neural_runs-<name>.json`` (every number, with the runs' configs),
* ``docs/images/neural/<name>.png``: a row per held-out view of the **last** run (render, ground truth,
  |error| × 4) and the train/val PSNR curves of every run,

and prints a Markdown table (with the full val split's metrics where ``python train.py eval --run DIR --split
val`` has written ``eval_val/``).

    python -m benchmarks.neural_runs --name lego-200 --split test \\
        40k=runs/lego-40k final=runs/lego --views 4
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import yaml
from matplotlib.figure import Figure

from benchmarks.common import IMAGES as ALL_IMAGES
from benchmarks.common import write_result

IMAGES = ALL_IMAGES / "neural"


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def summary(label: str, run: Path, split: str) -> dict:
    """Everything the table and the figure need from one run folder."""
    history = (_read(run / "history.json") or {}).get("history", [])
    metrics = _read(run / f"eval_{split}" / "metrics.json")
    if metrics is None:
        raise SystemExit(f"{run}: no eval_{split}/metrics.json (unfinished run?)")
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    return {"label": label, "run": str(run), "config": cfg, "history": history, split: metrics,
            "val": _read(run / "eval_val" / "metrics.json"), "geometry": _read(run / "eval_geometry.json"),
            "timing": _read(run / "timing.json"),
            "per_view": (_read(run / f"eval_{split}" / "per_view.json") or {}).get("views", [])}


def table(rows: list[dict], split: str) -> str:
    out = [f"| run | points | stage 1 alone val / {split} | val PSNR (history, last) | full val split | "
           f"{split} PSNR | {split} SSIM | draws | stage 1 s | stage 2 s | total s |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    nan = float("nan")
    for r in rows:
        g, m, t, v = r["geometry"] or {}, r[split], r["timing"] or {}, r["val"]
        last = r["history"][-1] if r["history"] else {}
        geo = f"{g['val']['psnr']['mean']:.2f} / {g[split]['psnr']['mean']:.2f}" if "val" in g and split in g else "–"
        full_val = f"{v['psnr']['mean']:.2f}" if v else "–"
        out.append(f"| {r['label']} | {m.get('points', '–')} | {geo} | {last.get('val_psnr', nan):.2f} "
                   f"(step {last.get('step', '–')}) | {full_val} | {m['psnr']['mean']:.2f} ± {m['psnr']['std']:.2f} | "
                   f"{m['ssim']['mean']:.4f} | {m.get('draws', 1)} | {t.get('geometry_s', nan):.0f} | "
                   f"{t.get('neural_steps_s', nan):.0f} | {t.get('train_total_s', nan):.0f} |")
    return "\n".join(out)


def view_grid(fig, run: Path, per_view: list[dict], split: str = "test", rows: int = 4) -> None:
    """Columns of ``fig`` (a ``rows``-row grid): per held-out view of ``run``, its render, the ground truth and
    |error| × 4 (rows 1–3; ``per_view`` from the run's ``eval_<split>/per_view.json``)."""
    views = len(per_view)
    for i, v in enumerate(per_view):
        stem = Path(v["name"]).name
        img = iio.imread(run / f"eval_{split}" / f"{stem}.png").astype(np.float32) / 255
        gt = iio.imread(run / f"eval_{split}" / f"{stem}_gt.png").astype(np.float32) / 255
        for j, (pic, label) in enumerate(((img, f"{v['psnr']:.2f} dB"), (gt, "ground truth"),
                                          (np.clip(np.abs(img - gt).mean(-1) * 4, 0, 1), "|error| × 4"))):
            ax = fig.add_subplot(rows, views, j * views + i + 1)
            ax.imshow(pic, cmap="magma" if j == 2 else None, vmin=0, vmax=1, interpolation="nearest")
            ax.set_title(f"{stem}: {label}", fontsize=8)
            ax.axis("off")


def plot_curves(ax, curves: list[tuple[str, list[dict]]]) -> None:
    """Train (solid) and val (dashed) PSNR over stage-2 steps of each ``(label, history)``."""
    for label, history in curves:
        steps = [h["step"] for h in history]
        line, = ax.plot(steps, [h["train_psnr"] for h in history], "-", label=f"{label} train")
        ax.plot(steps, [h["val_psnr"] for h in history], "--", color=line.get_color(), label=f"{label} val")
    ax.set_xlabel("stage-2 step")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=4)


def save(fig, path: Path, title: str) -> None:
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def figure(rows: list[dict], split: str, views: int, path: Path, title: str) -> None:
    """The last run's held-out views (render, ground truth, error) above every run's PSNR curves."""
    fig = Figure(figsize=(3 * max(views, 2), 9.5))
    view_grid(fig, Path(rows[-1]["run"]), rows[-1]["per_view"][:views], split)
    plot_curves(fig.add_subplot(4, 1, 4), [(r["label"], r["history"]) for r in rows])
    save(fig, path, title)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="label=run_folder, in the order of the table (the last one is drawn)")
    ap.add_argument("--name", required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--views", type=int, default=4)
    args = ap.parse_args()
    rows = []
    for spec in args.runs:
        label, _, folder = spec.partition("=")
        rows.append(summary(label, Path(folder), args.split))
    text = table(rows, args.split)
    write_result(f"neural_runs-{args.name}", {"command": "python -m benchmarks.neural_runs " + " ".join(sys.argv[1:]),
                                              "runs": [{k: v for k, v in r.items() if k != "per_view"} for r in rows],
                                              "markdown": text}, text)
    figure(rows, args.split, args.views, IMAGES / f"{args.name}.png",
           f"{args.name}: {rows[-1]['label']} on held-out {args.split} views; PSNR over stage-2 steps")


if __name__ == "__main__":
    main()
