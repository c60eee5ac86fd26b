"""The neural-rendering recipe, one change at a time (issue 12): stage 1 alone, then stage 2 from a shared
stage-1 geometry, each variant with several seeds; selection happens on val, test is only reported.

Stage-1 variants run the main job's stage 1 with overrides (``neural.steps=1``) and report the fitted RGB
surfels alone (``eval_geometry.json``: the point-based baseline the U-Net must beat). Stage-2 variants
start from the ``final`` stage-1 geometry (``geometry.init=ply``) and train the main job's stage 2 with
overrides, per seed (the seed changes the stage-2 feature init, batches and op samples).

    python benchmarks/neural_recipe.py                                   # the default scene, 64²
    python benchmarks/neural_recipe.py --stage1 final --stage2 final l1 --seeds 0 1

Writes ``benchmarks/results/neural_recipe-<config>.json``, prints Markdown tables, and draws
``docs/images/neural/recipe-<config>.png`` (test renders, ground truth and error of the final recipe;
train/val PSNR curves of the stage-2 variants). Wall times are printed with the load average.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from neural_runs import plot_curves, save, view_grid  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
IMAGES = REPO / "docs" / "images" / "neural"

#: Stage-1 variants: overrides of the config's geometry stage (docs/results.md, "The recipe").
DENSIFY = ["geometry.optim.densify.enabled=true", "geometry.optim.densify.start=2", "geometry.optim.densify.every=2",
           "geometry.optim.densify.stop=12", "geometry.optim.densify.grad_threshold=0.05",
           "geometry.optim.densify.max_growth=0.3"]
STAGE1: dict[str, list[str]] = {
    "final": [],
    "batch4-10ep": ["geometry.optim.batch=4", "geometry.optim.epochs=10"],
    "batch1-10ep": ["geometry.optim.epochs=10"],
    "densify": DENSIFY,
}
#: Stage-2 variants: overrides of the config's neural stage (all start from stage 1 "final").
STAGE2: dict[str, list[str]] = {
    "final": [],
    "l1-only": ["neural.gan.enabled=false", "neural.ssim_weight=0.0"],
    "gan-from-start": ["neural.gan.start=0.0", "neural.gan.weight=1.0", "neural.ssim_weight=0.0"],
}


def _load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def train(run: Path, args: argparse.Namespace, overrides: list[str]) -> dict:
    """``python train.py --config C --run run overrides`` (reused when finished); wall/CPU seconds."""
    done = run / "timing.json"
    if done.is_file() and (run / "eval_geometry.json").is_file():
        return json.loads((run.parent / f"{run.name}.time.json").read_text())
    cmd = [sys.executable, str(REPO / "train.py"), "--config", str(args.config), "--run", str(run), "--overwrite",
           "log.progress=false", *args.extra, *overrides]
    run.parent.mkdir(parents=True, exist_ok=True)
    load0, t0 = _load(), time.perf_counter()
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(run.parent / f"{run.name}.log", "w") as fh:
        proc = subprocess.run(cmd, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {proc.returncode}); see {run.parent / (run.name + '.log')}")
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = {"wall_s": time.perf_counter() - t0, "cpu_s": (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime),
         "load_before": load0, "load_after": _load()}
    (run.parent / f"{run.name}.time.json").write_text(json.dumps(t))
    return t


def stage1(name: str, args: argparse.Namespace, root: Path) -> dict:
    """One stage-1 variant: the fitted RGB surfels alone on val and test."""
    run = root / f"stage1-{name}"
    t = train(run, args, ["neural.steps=1", "log.validate=0", "eval.images=false", *STAGE1[name]])
    geo = json.loads((run / "eval_geometry.json").read_text())
    timing = json.loads((run / "timing.json").read_text())
    return {"name": name, "overrides": STAGE1[name], "points": geo["points"], "val_psnr": geo["val"]["psnr"],
            "test_psnr": geo["test"]["psnr"], "test_ssim": geo["test"]["ssim"], "geometry_s": timing["geometry_s"],
            **t, "run": str(run)}


def stage2(name: str, seed: int, ply: Path, args: argparse.Namespace, root: Path) -> dict:
    """One stage-2 variant and seed, from the shared geometry ``ply``."""
    run = root / f"stage2-{name}-s{seed}"
    over = ["geometry.init=ply", f"geometry.ply={ply}", "geometry.optim.epochs=0", f"seed={seed}", *STAGE2[name]]
    t = train(run, args, over)
    m = json.loads((run / "eval_test" / "metrics.json").read_text())
    hist = json.loads((run / "history.json").read_text())["history"]
    timing = json.loads((run / "timing.json").read_text())
    return {"name": name, "seed": seed, "overrides": STAGE2[name], "test_psnr": m["psnr"], "test_ssim": m["ssim"],
            "val_psnr": hist[-1]["val_psnr"], "train_psnr": hist[-1]["train_psnr"], "history": hist,
            "stage2_s": timing["neural_steps_s"], **t, "run": str(run)}


def _mean(rows: list[dict], key: str) -> tuple[float, float]:
    vals = [r[key]["mean"] if isinstance(r[key], dict) else r[key] for r in rows]
    return float(np.mean(vals)), float(np.std(vals))


def tables(s1: list[dict], s2: list[dict]) -> str:
    """Markdown: stage-1 rows, then stage-2 variants averaged over seeds (per-seed values listed)."""
    out = ["| stage 1 variant | points | val PSNR | test PSNR | test SSIM | stage-1 s | wall s (CPU s) | load |",
           "|---|---|---|---|---|---|---|---|"]
    for r in s1:
        out.append(f"| {r['name']} | {r['points']} | {r['val_psnr']['mean']:.2f} | {r['test_psnr']['mean']:.2f} | "
                   f"{r['test_ssim']['mean']:.4f} | {r['geometry_s']:.0f} | {r['wall_s']:.0f} ({r['cpu_s']:.0f}) | "
                   f"{r['load_before']} → {r['load_after']} |")
    out += ["", "| stage 2 variant | seeds | val PSNR | test PSNR (per seed) | test SSIM | train PSNR | stage-2 s |",
            "|---|---|---|---|---|---|---|"]
    for name in dict.fromkeys(r["name"] for r in s2):
        rows = [r for r in s2 if r["name"] == name]
        v, t, ss, tr = _mean(rows, "val_psnr"), _mean(rows, "test_psnr"), _mean(rows, "test_ssim"), _mean(rows, "train_psnr")
        per = " / ".join(f"{r['test_psnr']['mean']:.2f}" for r in rows)
        out.append(f"| {name} | {len(rows)} | {v[0]:.2f} ± {v[1]:.2f} | {t[0]:.2f} ± {t[1]:.2f} ({per}) | "
                   f"{ss[0]:.4f} | {tr[0]:.2f} | {np.mean([r['stage2_s'] for r in rows]):.0f} |")
    return "\n".join(out)


def figure(s2: list[dict], title: str, path: Path, views: int = 4) -> None:
    """Row per test view of the final recipe (seed of its first run): render, ground truth, |error|×4;
    bottom: train/val PSNR over stage-2 steps of every variant's first seed."""
    final = next(r for r in s2 if r["name"] == "final")
    per_view = json.loads((Path(final["run"]) / "eval_test" / "per_view.json").read_text())["views"][:views]
    fig = plt.figure(figsize=(3 * views, 9.5))
    view_grid(fig, Path(final["run"]), per_view)
    firsts = [next(x for x in s2 if x["name"] == name) for name in dict.fromkeys(r["name"] for r in s2)]
    plot_curves(fig.add_subplot(4, 1, 4), [(r["name"], r["history"]) for r in firsts])
    save(fig, path, title)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=REPO / "configs" / "default.yaml")
    p.add_argument("--stage1", nargs="+", default=list(STAGE1), choices=list(STAGE1))
    p.add_argument("--stage2", nargs="+", default=list(STAGE2), choices=list(STAGE2))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    p.add_argument("--runs", type=Path, default=None, help="runs folder (default runs/bench-recipe-<config>)")
    p.add_argument("extra", nargs="*", help="extra config overrides for every run (key=value)")
    args = p.parse_args()
    stem = args.config.stem
    root = args.runs or REPO / "runs" / f"bench-recipe-{stem}"
    s1 = [stage1(name, args, root) for name in dict.fromkeys(["final", *args.stage1])]
    ply = root / "stage1-final" / "geometry.ply"
    s2 = [stage2(name, seed, ply, args, root) for name in args.stage2 for seed in args.seeds]
    table = tables(s1, s2)
    print(table)
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / f"neural_recipe-{stem}.json"
    out.write_text(json.dumps({"config": str(args.config), "extra": args.extra, "stage1": s1,
                               "stage2": s2, "markdown": table}, indent=1))
    if any(r["name"] == "final" for r in s2):
        figure(s2, f"{stem}: final recipe on held-out test views; PSNR over stage-2 steps", IMAGES / f"recipe-{stem}.png")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
