"""Time to quality: validation PSNR against training wall time for the shipped recipes and one change each
(renderer, estimator, samples per pixel, point-only or neural), with the held-out test PSNR at the end.

Each variant is one ``train.py`` run of a shipped config with the overrides of :data:`VARIANTS`, one after
another (never two at once on a 2-core machine). A run's curve joins stage 1 (``geometry_history.json``: the
surfels rendered on val) and stage 2 (``history.json``: the U-Net's renders on val); its x axis is the training
wall time so far (stage 1 from before the initial points, plus the stage-2 step times) without the validation
renders. ``--budgets`` reads every curve at those seconds (the equal-time comparison).

    python -m benchmarks.time_to_quality --scene default                      # every default-scene variant
    python -m benchmarks.time_to_quality --scene lego --variants point point-m64 --seeds 0 1
    python -m benchmarks.time_to_quality --scene default --report             # table + figure of finished runs
    python -m benchmarks.time_to_quality --scene lego_400 --variants shipped   # lego at 400², up to an hour

Runs go to ``runs/ttq/<scene>/<variant>-s<seed>`` (a finished run is not trained again); the table to stdout and
``benchmarks/results/time_to_quality-<scene>.json``, the figure to ``docs/images/neural/time_to_quality-<scene>.png``.
The study that chose today's recipes (a hundred variants over eight rounds) ran at commit 5a3af74:
``benchmarks/time_to_quality.py`` there (docs/history.md).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure

from benchmarks.common import IMAGES, REPO, run_config, val_curve, write_result

#: Scene → (neural config, point-only config or ``None``, stage-1 / stage-2 validation cadences: dense enough for
#: a curve).
SCENES = {"default": ("default.yaml", "splat_only.yaml", ["geometry.log.validate=100", "log.validate=100"]),
          "lego": ("lego.yaml", "lego_splat_only.yaml", ["geometry.log.validate=360", "log.validate=125"]),
          "lego_400": ("lego_400.yaml", None, ["geometry.log.validate=240", "log.validate=125"])}
#: Variant → (which config of the scene: ``neural`` or ``point``, overrides of it). One change each.
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "shipped": ("neural", []),
    "ht": ("neural", ["render.estimator=ht"]),
    "truncated": ("neural", ["render.renderer=truncated"]),
    "m16": ("neural", ["render.samples=16"]),
    "m64": ("neural", ["render.samples=64"]),
    "point": ("point", []),
    "point-ht": ("point", ["render.estimator=ht"]),
    "point-truncated": ("point", ["render.renderer=truncated"]),
    "point-m16": ("point", ["render.samples=16"]),
    "point-m64": ("point", ["render.samples=64"]),
    # the length of the schedule (epochs; the annealing tail 1/6 of them, the rate's halvings at 1/3 and 2/3):
    # one recipe per time budget
    "point-e24": ("point", ["geometry.optim.epochs=24", "geometry.optim.anneal_epochs=4"]),
    "point-e48": ("point", ["geometry.optim.epochs=48", "geometry.optim.anneal_epochs=8"]),
    "e72": ("neural", ["geometry.optim.epochs=72", "geometry.optim.anneal_epochs=12"]),
    "e120": ("neural", ["geometry.optim.epochs=120", "geometry.optim.anneal_epochs=20"]),
}
#: Budgets (seconds) at which the curves are read, per scene.
BUDGETS = {"default": [60, 90, 120, 180], "lego": [300, 600, 900, 1200, 1500, 1800, 2100],
           "lego_400": [600, 1200, 1800, 2400, 3000, 3600]}


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def run_dir(scene: str, variant: str, seed: int) -> Path:
    return REPO / "runs" / "ttq" / scene / f"{variant}-s{seed}"


def train(scene: str, variant: str, seed: int) -> None:
    """Train one variant (skipped when its run folder holds a finished run)."""
    run = run_dir(scene, variant, seed)
    if (run / "timing.json").is_file():
        return
    neural, point, cadence = SCENES[scene]
    kind, overrides = VARIANTS[variant]
    if kind == "point" and point is None:
        raise SystemExit(f"--variants: {variant} trains the point-only config, and scene {scene} has none")
    ran = run_config(REPO / "configs" / (neural if kind == "neural" else point), run,
                     [f"seed={seed}", "log.progress=false", *cadence, *overrides])
    (run / "ttq.json").write_text(json.dumps(ran, indent=1))


def at_budget(pts: list[tuple[float, float]], budget: float) -> float:
    """Val PSNR of the last validation at or before ``budget`` seconds (nan when none)."""
    done = [p for t, p in pts if t <= budget]
    return done[-1] if done else float("nan")


def summary(scene: str, variant: str, seed: int) -> dict | None:
    """The finished run's record (``None`` when it has not finished)."""
    run = run_dir(scene, variant, seed)
    timing = _read(run / "timing.json")
    if timing is None:
        return None
    metrics, geometry = _read(run / "eval_test" / "metrics.json"), _read(run / "eval_geometry.json") or {}
    test = metrics["psnr"]["mean"] if metrics else geometry["test"]["psnr"]["mean"]
    return {"variant": variant, "seed": seed, "config": VARIANTS[variant], "train_s": timing["train_total_s"],
            "stage1_s": timing["geometry_s"], "stage1_test_psnr": geometry.get("test", {}).get("psnr", {}).get("mean"),
            "test_psnr": test, "points": metrics["points"] if metrics else geometry.get("points"),
            "curve": val_curve(run), **(_read(run / "ttq.json") or {})}


def front(rows: list[dict], budgets: list[float]) -> list[dict]:
    """Per budget, the finished run (of those trained within it) with the best final val PSNR, and its test
    PSNR: the time-to-quality front, selected on validation."""
    out = []
    for b in budgets:
        done = [r for r in rows if r["train_s"] <= b and r["curve"]]
        best = max(done, key=lambda r: r["curve"][-1][1], default=None)
        out.append({"budget_s": b, "variant": best and best["variant"], "seed": best and best["seed"],
                    "train_s": best and best["train_s"], "val_psnr": best and best["curve"][-1][1],
                    "test_psnr": best and best["test_psnr"]})
    return out


def front_table(rows: list[dict]) -> str:
    out = ["| budget | run (selected on val) | train s | final val PSNR | test PSNR |", "|---|---|---|---|---|"]
    for f in rows:
        if f["variant"] is None:
            out.append(f"| {f['budget_s'] / 60:.0f} min | none finished | | | |")
        else:
            out.append(f"| {f['budget_s'] / 60:.0f} min | {f['variant']} s{f['seed']} | {f['train_s']:.0f} | "
                       f"{f['val_psnr']:.2f} | {f['test_psnr']:.2f} |")
    return "\n".join(out)


def table(rows: list[dict], budgets: list[float]) -> str:
    head = "| variant | seed | train s (wall / CPU of the command) | stage 1 s | points | " + \
        " | ".join(f"val @ {b:.0f} s" for b in budgets) + " | stage-1 test | test PSNR |"
    out = [head, "|" + "---|" * (8 + len(budgets))]
    for r in rows:
        cells = " | ".join(f"{at_budget(r['curve'], b):.2f}" for b in budgets)
        s1 = r["stage1_test_psnr"]
        out.append(f"| {r['variant']} | {r['seed']} | {r['train_s']:.0f} ({r.get('wall_s', float('nan')):.0f} / "
                   f"{r.get('cpu_s', float('nan')):.0f}) | {r['stage1_s']:.0f} | {r['points']} | {cells} | "
                   f"{'–' if s1 is None else f'{s1:.2f}'} | {r['test_psnr']:.2f} |")
    return "\n".join(out)


def figure(rows: list[dict], scene: str, path: Path) -> None:
    """Val PSNR over training wall time, one line per run."""
    fig = Figure(figsize=(9, 5.5))
    ax = fig.subplots()
    colours: dict[str, tuple] = {}
    for r in rows:
        if not r["curve"]:
            continue
        t, p = zip(*r["curve"])
        colour = colours.setdefault(r["variant"], colormaps["tab20"](len(colours) % 20))
        first = r["seed"] == min(x["seed"] for x in rows if x["variant"] == r["variant"])
        ax.plot(np.array(t) / 60, p, "-o", ms=2.5, color=colour,
                label=f"{r['variant']} (test {r['test_psnr']:.2f})" if first else None)
    ax.set_xlabel("training wall time (min)")
    ax.set_ylabel("val PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(f"time to quality, {scene} scene")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", choices=sorted(SCENES), default="default")
    p.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS), metavar="NAME")
    p.add_argument("--seeds", nargs="*", type=int, default=[0])
    p.add_argument("--budgets", nargs="*", type=float, default=None, help="seconds (default: the scene's)")
    p.add_argument("--report", action="store_true", help="only tabulate the finished runs")
    args = p.parse_args()
    if not args.report:
        for variant in args.variants:
            for seed in args.seeds:
                train(args.scene, variant, seed)
                print(f"done: {variant} seed {seed}", flush=True)
    rows = [r for v in VARIANTS for seed in range(10) if (r := summary(args.scene, v, seed)) is not None]
    budgets = args.budgets or BUDGETS[args.scene]
    best = front(rows, budgets)
    text = table(rows, budgets) + "\n\n" + front_table(best)
    write_result(f"time_to_quality-{args.scene}", {"scene": args.scene, "budgets_s": budgets, "runs": rows,
                                                  "front": best}, text)
    figure(rows, args.scene, IMAGES / "neural" / f"time_to_quality-{args.scene}.png")


if __name__ == "__main__":
    main()
