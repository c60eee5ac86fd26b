"""Time to quality (issue 28): validation PSNR against training wall time for each renderer, estimator,
sample count, network size and stage split, with the held-out test PSNR at the end.

Each configuration is one ``train.py`` run of a shipped config with overrides, one after another (never
two at once: the machine has 2 cores). The curve of a run joins stage 1 (``geometry_history.json``: the
RGB/SH surfels rendered on val) and stage 2 (``history.json``: the U-Net's renders on val); its x axis is
the training wall time so far (stage 1 from before the visual hull, plus the stage-2 step times), without
the validation renders. ``--budget S`` reads every curve at S seconds (the equal-wall-time comparison).

    python benchmarks/time_to_quality.py --scene default --configs shipped m16 truncated --seeds 0 1 2
    python benchmarks/time_to_quality.py --scene lego --configs point-sh3 --seeds 0
    python benchmarks/time_to_quality.py --scene default --report          # table + figure of finished runs

Runs go to ``runs/ttq/<scene>/<config>-s<seed>`` (kept: a finished run is not trained again); the table
goes to stdout and ``benchmarks/results/time_to_quality-<scene>.json``, the figure to
``docs/images/neural/time_to_quality-<scene>.png``. Each run records wall and CPU seconds and the load
average before and after it.
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

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
IMAGES = REPO / "docs" / "images" / "neural"
SCENES = {"default": "configs/default.yaml", "lego": "configs/lego.yaml"}

#: Stage-1 validation cadence (fitter steps) and stage-2 cadence per scene: dense enough for a curve.
CADENCE = {"default": ["geometry.log.validate=100", "log.validate=100"],
           "lego": ["geometry.log.validate=120", "log.validate=250"]}
POINT_ONLY = ["neural.steps=0"]
SH = ["geometry.optim.shading=sh", "geometry.sh_degree=3"]
#: The stage-1 levers measured on lego 200² (docs/results.md, "Stage 1 on lego"): the sampled estimator,
#: surfels half the 3-NN spacing and a 0.3 px² screen-space low-pass instead of 1 px².
SHARP = ["render.estimator=sampled", "geometry.scale_factor=0.5", "render.lowpass=0.3"]

#: Configurations: overrides of the scene's shipped config as it was when the run was made (so a row of an
#: earlier session reruns the same only with the settings shipped since undone: e.g. lego rows before session
#: 7 ran without the annealing tail and with point features at 0.01, now `configs/lego.yaml`'s defaults;
#: add `geometry.optim.anneal_epochs=0` and `neural.learn=…` to reproduce them). "point-*" rows are stage 1
#: alone (no U-Net).
CONFIGS: dict[str, list[str]] = {
    "shipped": [],  # the shipped config as it was when the run was made (default: issue 28 session 1)
    "main-job": [],  # configs/default.yaml since issue 28 session 2 (sharp stage 1, U-Net width 16, 500 steps)
    "sampled": ["render.estimator=sampled"],
    "ht-pips": ["render.estimator=ht-pips"],
    "truncated": ["render.renderer=truncated"],
    "m8": ["render.samples=8"],
    "m16": ["render.samples=16"],
    "eps0.05": ["render.eps=0.05"],
    "unet-w16": ["neural.unet.width=16"],
    "unet-d3": ["neural.unet.depth=3"],
    "steps-half": ["neural.steps=500"],
    "no-gan": ["neural.gan.enabled=false"],
    "fast": ["render.estimator=sampled", "neural.steps=500"],
    "fast-s1half": ["render.estimator=sampled", "neural.steps=500", "geometry.optim.epochs=10"],
    "point": POINT_ONLY,
    "point-sampled": POINT_ONLY + ["render.estimator=sampled"],
    "point-truncated": POINT_ONLY + ["render.renderer=truncated"],
    "point-sh3": POINT_ONLY + SH,
    "point-sharp": POINT_ONLY + SHARP,
    "point-sharp-24ep": POINT_ONLY + SHARP + ["geometry.optim.epochs=24"],
    "sharp": SHARP,
    "sharp-w16": SHARP + ["neural.unet.width=16"],
    "sharp-w16-1000": SHARP + ["neural.unet.width=16", "neural.steps=1000"],
    "sharp-500": SHARP + ["neural.steps=500"],
    "sharp-w16-500": SHARP + ["neural.unet.width=16", "neural.steps=500"],
    "sharp-w16-400": SHARP + ["neural.unet.width=16", "neural.steps=400"],
    "sharp-w16-500-e12": SHARP + ["neural.unet.width=16", "neural.steps=500", "geometry.optim.epochs=12"],
}
#: Stage-2 point-feature rates before session 7 (``configs/lego.yaml`` now learns the features at 0.003).
F001 = "neural.learn={features: 0.01, means: 0.0001, opacities: 0.01}"
#: Stage 2 continued from a finished point-only run (same seed, same thread count): "<config>": (point-only
#: config, stage-2 overrides). The run loads that run's ``geometry.ply`` (no stage-1 fit of its own); its
#: curve is the point-only run's stage-1 curve followed by stage 2, offset by that run's stage-1 seconds, so
#: it reads as one uninterrupted training run (stage 1 is deterministic across thread counts: docs/op.md §4).
STAGE1_FROM: dict[str, tuple[str, list[str]]] = {
    "s1-24ep+s2-250": ("point-24ep", ["neural.steps=250", "neural.view_colour=false"]),
    "s1-24ep+s2-500": ("point-24ep", ["neural.steps=500", "neural.view_colour=false"]),
    "s1-24ep+s2-1000": ("point-24ep", ["neural.steps=1000", "neural.view_colour=false"]),
    "s1-24ep+s2-500-vc": ("point-24ep", ["neural.steps=500", "neural.view_colour=true"]),
    "s1-48ep+s2-500": ("point-48ep", ["neural.steps=500", "neural.view_colour=false"]),
    "s1-48ep+s2-500-vc": ("point-48ep", ["neural.steps=500", "neural.view_colour=true"]),
    "s1-48ep+s2-250-vc": ("point-48ep", ["neural.steps=250", "neural.view_colour=true"]),
    **{f"s1-{s1}+s2-{n}-vc": (f"point-{s1}", [f"neural.steps={n}", "neural.view_colour=true"])
       for s1 in ("48ep-norepo", "54ep-norepo", "72ep-norepo") for n in (250, 500)},
    # cheaper stage-2 steps for the 25-minute budget: one view per step, or fewer steps
    "s1-54ep-norepo+s2-250-vc-b1": ("point-54ep-norepo", ["neural.steps=250", "neural.view_colour=true",
                                                          "neural.batch=1"]),
    "s1-54ep-norepo+s2-160-vc": ("point-54ep-norepo", ["neural.steps=160", "neural.view_colour=true"]),
    **{f"s1-{s1}-op6+s2-{n}-vc{b}": (f"point-{s1}-op6", [f"neural.steps={n}", "neural.view_colour=true",
                                                         *(["neural.batch=1"] if b else [])])
       for s1 in ("54ep-norepo", "66ep-norepo", "72ep-norepo") for n in (250, 500) for b in ("", "-b1")},
    **{f"s1-{e}ep-norepo-cap05+s2-{n}-vc-b1": (f"point-{e}ep-norepo-cap05", [f"neural.steps={n}", "neural.view_colour=true",
                                                                          "neural.batch=1"])
       for e in (54, 66, 72) for n in (250, 500)},
    **{f"s1-{e}ep-norepo-cap05-a{a}+s2-{n}-vc-b1": (f"point-{e}ep-norepo-cap05-a{a}", [
        f"neural.steps={n}", "neural.view_colour=true", "neural.batch=1", F001])
       for e, a in ((54, 9), (72, 12), (72, 6), (72, 18)) for n in (250, 500)},
    # session 7: stage 2 on the annealed surfels (no PatchGAN; slower point features; 500 steps)
    **{f"s1-72ep-norepo-cap05-a12+s2-{n}-vc-b1-{v}": ("point-72ep-norepo-cap05-a12", [
        f"neural.steps={n}", "neural.view_colour=true", "neural.batch=1", *o])
       for n in (250, 500) for v, o in (("nogan", ["neural.gan.enabled=false", F001]),
                                        ("f003", ["neural.learn={features: 0.003, means: 0.0001, opacities: 0.01}"]))},
    # session 8: stage 2 that leaves the settled surfels where they are (features only), or a U-Net of width 8
    "s1-72ep-norepo-cap05-a12+s2-250-vc-b1-fonly": ("point-72ep-norepo-cap05-a12", [
        "neural.steps=250", "neural.view_colour=true", "neural.batch=1", "neural.learn={features: 0.003}"]),
    "s1-72ep-norepo-cap05-a12+s2-250-vc-b1-f003-w8": ("point-72ep-norepo-cap05-a12", [
        "neural.steps=250", "neural.view_colour=true", "neural.batch=1", "neural.unet.width=8"]),
    "s1-72ep-norepo-cap05-a12-or+s2-250-vc-b1-f003": ("point-72ep-norepo-cap05-a12-or", [
        "neural.steps=250", "neural.view_colour=true", "neural.batch=1",
        "neural.learn={features: 0.003, means: 0.0001, opacities: 0.01}"]),
    "point-24ep-eval": ("point-24ep", ["neural.steps=0"]),  # its surfels re-evaluated (eval.draws averaged)
    "s1-24ep+s2-250-lowlr": ("point-24ep", ["neural.steps=250", "neural.view_colour=false",
                                            "neural.learn={features: 0.001, means: 0.00001, opacities: 0.001}"]),
    "s1-24ep+s2-250-f3": ("point-24ep", ["neural.steps=250", "neural.features=3", "neural.view_colour=false"]),
}
#: Stage 1 without validation renders and without repositioning checks (session 5's lego runs).
NOREPO = ["geometry.log.validate=0", "geometry.optim.reposition=false"]
#: "-noval" runs skip the stage-1 validation renders, as the shipped configs do: their time is that of the
#: config's own training command (no curve, the held-out test at the end only).
CONFIGS.update({"point-12ep": POINT_ONLY + ["geometry.optim.epochs=12"],
                "point-40ep-noval": POINT_ONLY + ["geometry.optim.epochs=40", "geometry.log.validate=0"],
                # the rate halved 7 or 4 times instead of 5 over the 36 epochs
                "point-36ep-d7-noval": POINT_ONLY + ["geometry.optim.epochs=36", "geometry.optim.lr_decays=7",
                                                     "geometry.log.validate=0"],
                "point-36ep-d4-noval": POINT_ONLY + ["geometry.optim.epochs=36", "geometry.optim.lr_decays=4",
                                                     "geometry.log.validate=0"],
                "point-24ep": POINT_ONLY + ["geometry.optim.epochs=24"],
                # session 5: no repositioning checks (on lego they moved 0-7 of 78 496 points per run
                # and cost 13-17 s each, one every 4 epochs); "-c<C>": the first C epochs at 100x100
                **{f"point-{e}ep-norepo": POINT_ONLY + NOREPO + [f"geometry.optim.epochs={e}"]
                   for e in (40, 42, 48, 54, 72)},
                **{f"point-{e}ep-norepo-c{c}": POINT_ONLY + NOREPO + [f"geometry.optim.epochs={e}",
                                                                     f"geometry.optim.coarse_epochs={c}"]
                   for e, c in ((40, 16), (48, 24))},
                # session 6: every tangent std-dev capped (world units; the fitted median is 0.0065)
                **{f"point-{e}ep-norepo-cap{c}": POINT_ONLY + NOREPO + [f"geometry.optim.epochs={e}",
                                                                       f"geometry.optim.max_scale=0.{c}"]
                   for e in (54, 60, 66, 72) for c in ("05", "03", "02")},
                # the same overrides run with the session-6 op (scale classes lead the tree's sort key)
                **{f"point-{e}ep-norepo-op6": POINT_ONLY + NOREPO + [f"geometry.optim.epochs={e}"]
                   for e in (54, 66, 72)},
                # the rate halved once (after half the epochs) or never, instead of twice
                **{f"point-{e}ep-norepo-op6-d{d}": POINT_ONLY + NOREPO + [f"geometry.optim.epochs={e}",
                                                                         f"geometry.optim.lr_decays={d}"]
                   for e in (54, 72) for d in (0, 1)},
                # session 7: the last A epochs anneal the rate geometrically to 1/16 of the step schedule's
                **{f"point-{e}ep-norepo-cap05-a{a}": POINT_ONLY + NOREPO + [
                    f"geometry.optim.epochs={e}", "geometry.optim.max_scale=0.05", f"geometry.optim.anneal_epochs={a}",
                    "geometry.optim.anneal_factor=0.0625"] for e, a in ((54, 9), (60, 10), (72, 12), (72, 6), (72, 18),
                                                                        (80, 13))},
                # ... and with 3DGS's opacity reset after epochs 18 and 36 (every opacity lowered to 0.01)
                "point-72ep-norepo-cap05-a12-or": POINT_ONLY + NOREPO + [
                    "geometry.optim.epochs=72", "geometry.optim.max_scale=0.05", "geometry.optim.anneal_epochs=12",
                    "geometry.optim.anneal_factor=0.0625", "geometry.optim.opacity_resets=[18, 36]"],
                "point-36ep": POINT_ONLY + ["geometry.optim.epochs=36"],
                "point-48ep": POINT_ONLY + ["geometry.optim.epochs=48"]})
CONFIGS.update({name: o for name, (_, o) in STAGE1_FROM.items()})
#: The paper's thesis (issue 28 item 2): stage 1 alone from a poor start, per renderer/estimator.
POOR_STARTS = {"random": ["geometry.init=random", "geometry.max_points=2400"], "tenth": ["geometry.init_fraction=0.1"],
               "shift3": ["geometry.init_shift=3"]}
#: The estimator is explicit: `configs/default.yaml` itself moved from `ht` to `sampled` (session 2), after the
#: random/tenth rows had run with `ht` as the config's own estimator.
RENDERERS = {"ht": ["render.estimator=ht"], "sampled": ["render.estimator=sampled"],
             "truncated": ["render.renderer=truncated"]}
#: "poor-*" ran in session 1 on the default config of that time (blurry surfels: std = spacing, 1 px² low-pass);
#: "poor-*-sharp" (session 8) the same overrides on today's default (std ½ spacing, 0.3 px² low-pass).
CONFIGS.update({f"poor-{start}-{r}{tag}": POINT_ONLY + s + o for start, s in POOR_STARTS.items()
                for r, o in RENDERERS.items() for tag in ("", "-sharp")})


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def run_one(scene: str, name: str, seed: int, extra: list[str], cpus: str | None = None) -> Path:
    """Train one configuration (skipped when its run folder already holds a finished run); ``cpus``: pin it
    to these cores (``taskset -c``) with one thread per core (default: the machine's, 2 threads)."""
    run = REPO / "runs" / "ttq" / scene / f"{name}-s{seed}"
    if (run / "timing.json").is_file():
        return run
    if name in STAGE1_FROM:
        ply = REPO / "runs" / "ttq" / scene / f"{STAGE1_FROM[name][0]}-s{seed}" / "geometry.ply"
        if not ply.is_file():
            raise SystemExit(f"{name}: run {STAGE1_FROM[name][0]} (seed {seed}) first; {ply} is missing")
        extra = ["geometry.init=ply", f"geometry.ply={ply}", "geometry.optim.epochs=0", *extra]
    cmd = [sys.executable, str(REPO / "train.py"), "--config", str(REPO / SCENES[scene]), "--run", str(run),
           "--overwrite", f"seed={seed}", "log.progress=false", *CADENCE[scene], *CONFIGS[name], *extra]
    env = dict(os.environ)
    if cpus:
        cmd = ["taskset", "-c", cpus, *cmd]
        env["OMP_NUM_THREADS"] = str(len(cpus.split(",")))
    before, t0 = _load(), time.perf_counter()
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{name} seed {seed} failed:\n{proc.stderr[-3000:]}")
    (run / "ttq.json").write_text(json.dumps({
        "command": cmd[1:], "wall_s": time.perf_counter() - t0,
        "cpu_s": (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime),
        "load_before": before, "load_after": _load(), "threads": int(env.get("OMP_NUM_THREADS", "0")) or None,
        "cpus": cpus}, indent=1))
    return run


def curve(run: Path, stage1: Path | None = None) -> list[tuple[float, float]]:
    """``(training seconds, val PSNR)`` of stage 1 then stage 2; ``stage1``: the run whose stage 1 this one
    continues (:data:`STAGE1_FROM`), its curve and time come first."""
    geo = (_read((stage1 or run) / "geometry_history.json") or {}).get("history", [])
    pts = [(h["elapsed_s"], h["val_psnr"]) for h in geo]
    timing = _read(run / "timing.json") or {}
    offset = timing.get("geometry_s", 0.0) + ((_read(stage1 / "timing.json") or {}).get("geometry_s", 0.0)
                                              if stage1 else 0.0)
    pts += [(offset + h["elapsed_s"], h["val_psnr"]) for h in (_read(run / "history.json") or {}).get("history", [])]
    return pts


def at_budget(pts: list[tuple[float, float]], budget: float) -> float:
    """Val PSNR of the last validation at or before ``budget`` seconds (nan when none)."""
    done = [p for t, p in pts if t <= budget]
    return done[-1] if done else float("nan")


def summary(scene: str, name: str, seed: int) -> dict | None:
    run = REPO / "runs" / "ttq" / scene / f"{name}-s{seed}"
    timing = _read(run / "timing.json")
    if timing is None:
        return None
    split = "test"
    metrics = _read(run / f"eval_{split}" / "metrics.json")
    geometry = _read(run / "eval_geometry.json") or {}
    test = metrics["psnr"]["mean"] if metrics else geometry[split]["psnr"]["mean"]
    points = metrics["points"] if metrics else geometry.get("points")
    stage1 = REPO / "runs" / "ttq" / scene / f"{STAGE1_FROM[name][0]}-s{seed}" if name in STAGE1_FROM else None
    s1 = (_read(stage1 / "timing.json") or {}).get("geometry_s", 0.0) if stage1 else 0.0
    return {"config": name, "seed": seed, "overrides": CONFIGS[name],
            "stage1_from": STAGE1_FROM[name][0] if stage1 else None, "train_s": timing["train_total_s"] + s1,
            "stage1_s": timing["geometry_s"] + s1,
            "stage1_test_psnr": geometry.get(split, {}).get("psnr", {}).get("mean"),
            "test_psnr": test, "points": points, "curve": curve(run, stage1), **(_read(run / "ttq.json") or {})}


def table(rows: list[dict], budgets: list[float]) -> str:
    head = "| config | seed | train s (wall / CPU of the command) | stage 1 s | points | " + \
        " | ".join(f"val @ {b:.0f} s" for b in budgets) + " | stage-1 test | test PSNR |"
    out = [head, "|" + "---|" * (8 + len(budgets) - 2)]
    for r in rows:
        cells = " | ".join(f"{at_budget(r['curve'], b):.2f}" for b in budgets)
        s1 = r["stage1_test_psnr"]
        out.append(f"| {r['config']} | {r['seed']} | {r['train_s']:.0f} ({r.get('wall_s', float('nan')):.0f} / "
                   f"{r.get('cpu_s', float('nan')):.0f}) | {r['stage1_s']:.0f} | {r['points']} | {cells} | "
                   f"{'–' if s1 is None else f'{s1:.2f}'} | {r['test_psnr']:.2f} |")
    return "\n".join(out)


def figure(rows: list[dict], scene: str, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(9, 5.5))
    colours: dict[str, tuple] = {}
    for r in rows:
        if not r["curve"]:
            continue
        t, p = zip(*r["curve"])
        colour = colours.setdefault(r["config"], plt.cm.tab20(len(colours) % 20))
        ax.plot(np.array(t) / 60, p, "-o", ms=2.5, color=colour,
                label=f"{r['config']} (test {r['test_psnr']:.2f})" if r["seed"] == min(
                    x["seed"] for x in rows if x["config"] == r["config"]) else None)
    threads = {r.get("threads") or 2 for r in rows}
    ax.set_xlabel(f"training wall time (min, {'/'.join(map(str, sorted(threads)))} thread(s): see the JSON per run)")
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
    p.add_argument("--configs", nargs="*", default=[], choices=sorted(CONFIGS), metavar="NAME")
    p.add_argument("--seeds", nargs="*", type=int, default=[0])
    p.add_argument("--budgets", nargs="*", type=float, default=None, help="seconds (default: scene's)")
    p.add_argument("--cpus", default=None, help="pin runs to these cores, one thread each (e.g. 0 or 0,1)")
    p.add_argument("--report", action="store_true", help="only tabulate the finished runs")
    p.add_argument("--plot", nargs="*", default=None, metavar="NAME",
                   help="configurations drawn in the figure (default: every finished one)")
    p.add_argument("--figure", default=None, help="figure file stem (default: time_to_quality-<scene>)")
    args = p.parse_args()
    if not args.report:
        for name in args.configs:
            for seed in args.seeds:
                run_one(args.scene, name, seed, [], args.cpus)
                print(f"done: {name} seed {seed}", flush=True)
    rows = [r for name in CONFIGS for seed in range(10) if (r := summary(args.scene, name, seed)) is not None]
    budgets = args.budgets or ([60, 90, 120, 180] if args.scene == "default" else [300, 600, 900, 1500])
    print(table(rows, budgets))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"time_to_quality-{args.scene}.json").write_text(json.dumps(
        {"scene": args.scene, "budgets_s": budgets, "runs": rows}, indent=1))
    figure([r for r in rows if args.plot is None or r["config"] in args.plot], args.scene,
           IMAGES / f"{args.figure or f'time_to_quality-{args.scene}'}.png")


if __name__ == "__main__":
    main()
