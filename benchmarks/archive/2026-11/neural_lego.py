"""Neural rendering on NeRF-synthetic lego: held-out PSNR/SSIM and training time, one factor at a time.

(Any ``neural`` config works: ``--config configs/default.yaml --resolution 64`` runs the same study on
the embedded procedural scene.)

Stage 1 (RGB surfels on the visual hull, fitted with the op) runs once; every variant then trains
stage 2 from that geometry (``geometry.init=ply``, ``geometry.optim.epochs=0``) with
``python train.py --config configs/lego.yaml``, so the variants differ only in:

    base      L1 + PatchGAN, joint (features, positions, opacities learnable), estimator ht
    l1        L1 only (no discriminator)                                  (a) L1 vs L1+GAN
    frozen    features only (geometry frozen)                             (b) frozen vs joint
    sampled   estimator "sampled" (plain autograd through the sample)     (c) ht vs sampled

Each run logs train and val PSNR over steps (``history.json``; overfitting) and evaluates the test
split. Prints a Markdown table, writes ``benchmarks/results/neural_<config>-<res>.json`` and a figure
``docs/images/neural/<config>-<res>.png`` (test renders vs GT, PSNR curves), ``<config>`` being the
config file's stem (``lego``, ``default``).

    python benchmarks/neural_lego.py --resolution 200 --steps 600        # the CPU budget in docs
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from neural_runs import plot_curves, save  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
IMAGES = REPO / "docs" / "images" / "neural"
VARIANTS: dict[str, list[str]] = {
    "base": [],
    "l1": ["neural.gan.enabled=false"],
    "frozen": ["neural.learn={features: 0.01}"],
    "sampled": ["render.estimator=sampled"],
}


def train(run: Path, overrides: list[str], args: argparse.Namespace, log_name: str) -> float:
    """``python train.py --config <config> --run <run> overrides``; returns wall seconds."""
    cmd = [sys.executable, str(REPO / "train.py"), "--config", str(args.config), "--run", str(run),
           f"data.resolution={args.resolution}", "log.progress=false", *args.extra, *overrides]
    if args.resume and (run / "config.yaml").is_file():
        cmd = [sys.executable, str(REPO / "train.py"), "--run", str(run), "--resume"]
    run.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(run.parent / f"{log_name}.log", "w") as fh:
        proc = subprocess.run(cmd, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {proc.returncode}); see {run.parent / (log_name + '.log')}")
    return time.perf_counter() - t0


def geometry(args: argparse.Namespace, root: Path) -> tuple[Path, float]:
    """Stage 1 once: a run with one stage-2 step, whose ``geometry.ply`` the variants start from."""
    run = root / "geometry"
    ply = run / "geometry.ply"
    if ply.is_file() and (run / "timing.json").is_file():
        return ply, json.loads((run / "timing.json").read_text())["geometry_s"]
    train(run, ["neural.steps=1", "log.validate=0", "eval.images=false"], args, "geometry")
    return ply, json.loads((run / "timing.json").read_text())["geometry_s"]


def variant(name: str, ply: Path, args: argparse.Namespace, root: Path) -> dict:
    """Stage 2 of one variant; returns its metrics, history and timings."""
    run = root / name
    metrics_path = run / "eval_test" / "metrics.json"
    if not metrics_path.is_file():
        over = ["geometry.init=ply", f"geometry.ply={ply}", "geometry.optim.epochs=0", f"neural.steps={args.steps}",
                f"log.validate={args.validate}", f"log.images={args.validate}", f"log.checkpoint={args.validate}"]
        train(run, over + VARIANTS[name], args, name)
    m = json.loads(metrics_path.read_text())
    hist = json.loads((run / "history.json").read_text())
    timing = json.loads((run / "timing.json").read_text())
    return {"name": name, "overrides": VARIANTS[name], "test_psnr": m["psnr"], "test_ssim": m["ssim"],
            "lpips": m["lpips"], "points": m["points"], "history": hist["history"],
            "stage2_seconds": timing["neural_steps_s"], "run": str(run)}


def figure(rows: list[dict], title: str, path: Path) -> None:
    """Row 1: the first test view of each variant and GT; row 2: train/val PSNR over steps."""
    first = Path(json.loads((Path(rows[0]["run"]) / "eval_test" / "per_view.json").read_text())["views"][0]["name"]).name
    fig = plt.figure(figsize=(3 * (len(rows) + 1), 6))
    for i, r in enumerate(rows):
        ax = fig.add_subplot(2, len(rows) + 1, i + 1)
        ax.imshow(iio.imread(Path(r["run"]) / "eval_test" / f"{first}.png"))
        ax.set_title(f"{r['name']}: {r['test_psnr']['mean']:.2f} dB", fontsize=9)
        ax.axis("off")
    ax = fig.add_subplot(2, len(rows) + 1, len(rows) + 1)
    ax.imshow(iio.imread(Path(rows[0]["run"]) / "eval_test" / f"{first}_gt.png"))
    ax.set_title("ground truth", fontsize=9)
    ax.axis("off")
    plot_curves(fig.add_subplot(2, 1, 2), [(r["name"], r["history"]) for r in rows])
    save(fig, path, f"{title}: test view {first} and train/val PSNR over steps")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=REPO / "configs" / "lego.yaml")
    p.add_argument("--resolution", type=int, default=200)
    p.add_argument("--steps", type=int, default=600, help="stage-2 steps per variant")
    p.add_argument("--validate", type=int, default=100, help="steps between train/val PSNR evaluations")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--runs", type=Path, default=None, help="runs folder (default runs/bench-neural-<config>-<res>)")
    p.add_argument("--resume", action="store_true", help="resume unfinished runs instead of restarting them")
    p.add_argument("extra", nargs="*", help="extra config overrides for every run (key=value)")
    args = p.parse_args()
    args.config = args.config.resolve()
    stem = args.config.stem
    root = args.runs or REPO / "runs" / f"bench-neural-{stem}-{args.resolution}"
    root.mkdir(parents=True, exist_ok=True)
    ply, geo_s = geometry(args, root)
    rows = [variant(v, ply, args, root) for v in args.variants]
    lines = [f"{stem} {args.resolution}x{args.resolution}, {args.steps} stage-2 steps, stage 1 (shared): {geo_s:.0f} s, "
             f"threads: {os.environ.get('OMP_NUM_THREADS', 'default')}",
             "", "| variant | test PSNR (dB) | test SSIM | stage-2 time (s) | points | final train / val PSNR |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        h = r["history"][-1] if r["history"] else {}
        lines.append(f"| {r['name']} | {r['test_psnr']['mean']:.2f} ± {r['test_psnr']['std']:.2f} | "
                     f"{r['test_ssim']['mean']:.4f} ± {r['test_ssim']['std']:.4f} | {r['stage2_seconds']:.0f} | "
                     f"{r['points']} | {h.get('train_psnr', float('nan')):.2f} / {h.get('val_psnr', float('nan')):.2f} |")
    table = "\n".join(lines)
    print(table)
    out = RESULTS / f"neural_{stem}-{args.resolution}.json"
    RESULTS.mkdir(parents=True, exist_ok=True)
    config = args.config.relative_to(REPO) if args.config.is_relative_to(REPO) else args.config
    out.write_text(json.dumps({"config": str(config), "resolution": args.resolution, "steps": args.steps, "geometry_seconds": geo_s,
                               "extra": args.extra, "threads": os.environ.get("OMP_NUM_THREADS"),
                               "rows": rows, "markdown": table}, indent=1))
    fig = IMAGES / f"{stem}-{args.resolution}.png"
    figure(rows, f"{stem} {args.resolution}x{args.resolution}", fig)
    print(f"\nwrote {out} and {fig}")


if __name__ == "__main__":
    main()
