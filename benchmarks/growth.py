"""Growth during stage 1: density control (split, clone, prune by contribution, a point budget) from sparser
starts than the shipped hull, against the shipped stage 1, at equal epochs; selected on validation PSNR.

Each variant is one ``train.py`` run of a config with the overrides of :data:`VARIANTS`, one after another (never
two at once on a 2-core machine), under ``/usr/bin/time`` for the process's peak memory. The table gives, per run:
the epochs, the final stage-1 val PSNR (``geometry_history.json``: ``eval.val_views`` of the val views, as
the fitter validates; and on all of them, ``eval_geometry.json``), the run's final val PSNR (stage 2's
``history.json`` where the run has a U-Net, else stage 1's), the final point count, the fitter's per-point
state (the surfels' stored attributes, once for the parameters and twice for Adam's moments), the process's peak
resident memory, and the training wall / CPU seconds (the machine may be shared: compare at equal epochs).

    python -m benchmarks.growth --scene default                 # every variant of the main job
    python -m benchmarks.growth --scene lego --variants e24 g96-e24
    python -m benchmarks.growth --scene lego --report           # tabulate the finished runs

Runs go to ``runs/growth/<scene>/<variant>`` (a finished run is not trained again); the table to stdout and
``benchmarks/results/growth-<scene>.json``.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
from pathlib import Path

import yaml
from plyfile import PlyData

from benchmarks.common import REPO, markdown, run_config, write_result

#: Scene → (config, overrides every variant gets: the validation cadence (the last step always validates)).
SCENES = {"default": ("default.yaml", ["log.progress=false"]),
          "lego": ("lego_splat_only.yaml", ["log.progress=false", "geometry.log.validate=720"])}


def _grow(start: int, every: int, stop: int, threshold: float, split: float, growth: float, budget: int,
          prune_weight: float = 0.0) -> list[str]:
    """Overrides that turn density control on during stage 1."""
    return [f"geometry.optim.densify={{enabled: true, start: {start}, every: {every}, stop: {stop}, "
            f"grad_threshold: {threshold}, split_size: {split}, max_growth: {growth}, max_points: {budget}, "
            f"prune_opacity: 0.02, prune_weight: {prune_weight}}}"]


#: Variant → (scene, overrides). The default scene's stage 1 has 20 one-view epochs over 40 views (800 steps) from
#: the 96³ hull (about 2400 surfels); lego's ``eN`` rows are the shipped point-only recipe at N epochs (the rate
#: halves at 1/3 and 2/3, the tail anneals the last 1/6), ``gG-eN`` starts on the G³ hull and grows during the
#: first half of the epochs up to the 160³ hull's point count (80 000), splitting the 30 % with the largest
#: screen-space gradient per event; ``g160-120k-e24`` grows the shipped 160³ hull itself by the main job's rule
#: (split the 30 % with the largest gradient, up to 120 000 surfels, no pruning); ``g128-clone-e24`` clones the
#: 20 % with the largest gradient instead (same size, offset by half a std-dev), in the first third of the epochs
#: (defined, not measured yet).
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "shipped": ("default", []),
    "grow-4k": ("default", _grow(2, 2, 10, 0.0, 0.01, 0.3, 4000)),
    "grow-4k-prune": ("default", _grow(2, 2, 10, 0.0, 0.01, 0.3, 4000, prune_weight=0.5)),
    "grow-4k-s300": ("default", [*_grow(2, 2, 10, 0.0, 0.01, 0.3, 4000), "neural.steps=300"]),
    "grow-4k-s400": ("default", [*_grow(2, 2, 10, 0.0, 0.01, 0.3, 4000), "neural.steps=400"]),
    "shipped-seed1": ("default", ["seed=1"]),
    "grow-4k-s400-seed1": ("default", ["seed=1", *_grow(2, 2, 10, 0.0, 0.01, 0.3, 4000), "neural.steps=400"]),
    "e24": ("lego", ["geometry.optim.epochs=24", "geometry.optim.anneal_epochs=4"]),
    "g96-e24": ("lego", ["geometry.grid=96", "geometry.optim.epochs=24", "geometry.optim.anneal_epochs=4",
                         *_grow(2, 2, 12, 0.0, 0.0, 0.3, 80000, prune_weight=0.5)]),
    "g128-clone-e24": ("lego", ["geometry.grid=128", "geometry.optim.epochs=24", "geometry.optim.anneal_epochs=4",
                                *_grow(2, 2, 8, 0.0, 1.0, 0.2, 80000, prune_weight=0.5)]),
    "g160-120k-e24": ("lego", ["geometry.optim.epochs=24", "geometry.optim.anneal_epochs=4",
                               *_grow(2, 2, 12, 0.0, 0.01, 0.3, 120000)]),
}


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def run_dir(variant: str) -> Path:
    return REPO / "runs" / "growth" / VARIANTS[variant][0] / variant


def train(variant: str) -> None:
    """Train one variant (skipped when its run folder holds a finished run)."""
    run = run_dir(variant)
    if (run / "timing.json").is_file():
        return
    scene, overrides = VARIANTS[variant]
    config, common = SCENES[scene]
    time_cmd = shutil.which("time") or "/usr/bin/time"
    ran = run_config(REPO / "configs" / config, run, [*common, *overrides],
                     command=[time_cmd, "-f", "peak_rss_kb=%M", sys.executable, str(REPO / "train.py")])
    text = Path(ran["log"]).read_text(errors="replace")
    peak = re.findall(r"peak_rss_kb=(\d+)", text)
    ran["peak_rss_mb"] = int(peak[-1]) / 1024 if peak else None
    (run / "growth.json").write_text(json.dumps(ran, indent=1))


def summary(variant: str) -> dict | None:
    """The finished run's record (``None`` when it has not finished)."""
    run = run_dir(variant)
    timing = _read(run / "timing.json")
    if timing is None:
        return None
    geometry = (_read(run / "geometry_history.json") or {}).get("history", [])
    stage2 = (_read(run / "history.json") or {}).get("history", [])
    ply = PlyData.read(str(run / "geometry.ply"))["vertex"]
    points, row_bytes = len(ply.data), ply.data.dtype.itemsize
    metrics, geo_eval = _read(run / "eval_test" / "metrics.json"), _read(run / "eval_geometry.json") or {}
    ran = _read(run / "growth.json") or {}
    cfg = yaml.safe_load((run / "config.yaml").read_text()) if (run / "config.yaml").is_file() else {}
    return {"variant": variant, "overrides": VARIANTS[variant][1],
            "epochs": cfg.get("geometry", {}).get("optim", {}).get("epochs"),
            "stage1_val_psnr": geometry[-1]["val_psnr"] if geometry else None,
            "val_psnr": (stage2 or geometry)[-1]["val_psnr"] if (stage2 or geometry) else None,
            "stage1_val_all_psnr": geo_eval.get("val", {}).get("psnr", {}).get("mean"),
            "test_psnr": metrics["psnr"]["mean"] if metrics else geo_eval.get("test", {}).get("psnr", {}).get("mean"),
            "points": points, "state_mb": points * row_bytes * 3 / 2**20, "peak_rss_mb": ran.get("peak_rss_mb"),
            "stage1_s": timing.get("geometry_s"), "train_s": timing.get("train_total_s"),
            "wall_s": ran.get("wall_s"), "cpu_s": ran.get("cpu_s"), "load_before": ran.get("load_before"),
            "stage1_curve": [(h["step"], h["val_psnr"]) for h in geometry]}


def table(rows: list[dict]) -> str:
    def f(x, fmt="{:.2f}"):
        return "–" if x is None else fmt.format(x)
    return markdown(["variant", "epochs", "stage-1 val PSNR", "stage-1 val PSNR, all views", "final val PSNR", "test PSNR", "points", "state MB",
                     "peak RSS MB", "stage 1 s", "wall / CPU s"],
                    [[r["variant"], r["epochs"], f(r["stage1_val_psnr"]), f(r.get("stage1_val_all_psnr")), f(r["val_psnr"]), f(r["test_psnr"]),
                      r["points"], f(r["state_mb"], "{:.1f}"), f(r["peak_rss_mb"], "{:.0f}"),
                      f(r["stage1_s"], "{:.0f}"), f"{f(r['wall_s'], '{:.0f}')} / {f(r['cpu_s'], '{:.0f}')}"]
                     for r in rows])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", choices=sorted(SCENES), default="default")
    names = [v for v, (s, _) in VARIANTS.items()]
    p.add_argument("--variants", nargs="*", default=None, choices=names, metavar="NAME")
    p.add_argument("--report", action="store_true", help="only tabulate the finished runs")
    args = p.parse_args()
    variants = args.variants or [v for v in names if VARIANTS[v][0] == args.scene]
    if any(VARIANTS[v][0] != args.scene for v in variants):
        p.error(f"--variants: every variant must belong to --scene {args.scene}")
    if not args.report:
        for v in variants:
            train(v)
            print(f"done: {v}", flush=True)
    rows = [r for v in names if VARIANTS[v][0] == args.scene and (r := summary(v)) is not None]
    write_result(f"growth-{args.scene}", {"scene": args.scene, "runs": rows}, table(rows))


if __name__ == "__main__":
    main()
