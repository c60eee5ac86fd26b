"""A fair Table-1 comparison of the gradient estimators: the same learning-rate sweep for each.

Every estimator (``ht``, ``ht-pips``, ``paper``, ``sampled``) is run with each learning rate of ``--lrs``
(the rate of positions, normals, scales and features together) on each shape, at a Table-1 budget
(``--setting`` of :mod:`benchmarks.table1`). For each (shape, estimator) the rate is **selected on the final
training image loss** (the images the optimiser sees; the ground-truth geometry is never used to choose):
the L1 loss of the final scene on all training views, rendered with the exact dense renderer
(``train_loss_dense``, deterministic and the same measure for every estimator; the run's own
``final_loss``, its last step's batch of 6 views through the sampled forward, is reported beside it).
The selected run's Chamfer / Hausdorff distances to the ground-truth points are reported, and, for
information only, the rate with the best Chamfer ("oracle", not a selection).

    python -m benchmarks.estimator_sweep --shapes bunny teapot --jobs 1
    python -m benchmarks.estimator_sweep --setting cpu-long --shapes bunny
    python -m benchmarks.estimator_sweep --merge --jobs 1      # reuse the runs already in the JSON
    python -m benchmarks.estimator_sweep --merge --lrs 0.3     # add a rate to the existing sweep
    python -m benchmarks.estimator_sweep optim.batch=24 optim.epochs=80 optim.reposition.every=20 \
        --tag fullbatch --shapes bunny --estimators ht sampled --lrs 0.03 0.1   # a variant of the budget

``--merge`` loads ``benchmarks/results/estimator_sweep-<setting>.json`` and reuses its records (its runs'
folders may be gone): only the (shape, estimator, lr) combinations missing from it are run, and the JSON is
rewritten with all of them (records of shapes / estimators / rates outside this invocation are kept too).
A reused record keeps the ``overrides`` it was run with (``reused_overrides`` of the JSON) when they were
spelled differently (the pre-engine config vocabulary: ``optim.lr`` for every attribute). Records made by
an older version of the fitter are not comparable with new runs (its random streams differ: Chamfer moved
by up to ±5 % on the bunny); drop them from the JSON to have them re-run.

Writes ``benchmarks/results/estimator_sweep-<setting>.json`` (each run's record with its validation curve,
Chamfer / Hausdorff at its ``log.validate`` steps, while its folder exists) and prints a Markdown table;
``--curves`` prints the curves too. A seed other than 0 (``--seed``) belongs in its own ``--tag``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from benchmarks.common import RESULTS, machine
from benchmarks.table1 import SETTINGS, SHAPES, common_args, fmt, learning_rate, prepare_gt, run_one
from nsplat import render as gateway
from nsplat.config import load_config, read_yaml
from nsplat.data.dss import gt_views
from nsplat.data.pointclouds import load_dss_shape
from nsplat.engine import write_json
from nsplat.runctx import RunContext
from nsplat.shading import lambert
from nsplat.tasks.reconstruct import Config, restore

ESTIMATORS = ("ht", "ht-pips", "paper", "sampled")


def load_run(run_dir: Path):
    """A finished reconstruction run: ``(config, its training views (GT images), its final scene)``, on the CPU."""
    cfg = load_config(Config, read_yaml(run_dir / "config.yaml"))
    views = gt_views(load_dss_shape(cfg.data.shape, cfg.data.root or None), cfg.data, cfg.render, cfg.data.views)
    return cfg, views, restore(cfg, RunContext(run_dir=run_dir, device=torch.device("cpu"), seed=cfg.seed))


def dense_train_loss(run_dir: Path) -> float | None:
    """L1 loss of the run's final scene on **all** its training views, rendered with the exact dense renderer
    (deterministic, the same for every estimator; cached in ``train_loss_dense.json``). ``None`` when the
    run folder is gone. The selection criterion: the run's own ``final_loss`` is the last step's batch
    (6 of the 24 views, sampled forward), a noisier figure."""
    cache = run_dir / "train_loss_dense.json"
    if cache.is_file():
        return json.loads(cache.read_text())["train_loss_dense"]
    if not (run_dir / "checkpoints" / "latest").is_file():
        return None
    cfg, views, scene = load_run(run_dir)
    dense = dataclasses.replace(cfg.render, renderer="dense")
    with torch.no_grad():
        shaded = lambert(scene.features, scene.normals, views.viewmats)
        loss = sum(float((gateway.render(scene.means, scene.normals, scene.scales, scene.opacities, shaded[b],
                                         views.viewmats[b:b + 1], views.Ks[b:b + 1], cfg.data.width,
                                         cfg.data.height, dense).image[0] - views.images[b]).abs().mean())
                   for b in range(cfg.data.views)) / cfg.data.views
    cache.write_text(json.dumps({"train_loss_dense": loss}))
    return loss


def main() -> None:
    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--lrs", nargs="+", type=float, default=[0.01, 0.03, 0.1])
    extra.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=list(ESTIMATORS))
    extra.add_argument("--tag", default="",
                       help="a variant of the setting (extra overrides after the options): runs go to "
                            "runs/bench/sweep-<setting>-<tag>/, results to estimator_sweep-<setting>-<tag>.json")
    extra.add_argument("--merge", action="store_true",
                       help="reuse the records of the existing JSON; run only the missing combinations")
    extra.add_argument("--curves", action="store_true",
                       help="also print each run's Chamfer / Hausdorff at its validation steps")
    known, rest = extra.parse_known_args()
    sys.argv = [sys.argv[0]] + rest
    args = common_args(__doc__.splitlines()[0])
    jobs = [(f"{shape}-{est}-lr{lr:g}", shape, ["render.renderer=splat", f"render.estimator={est}", *learning_rate(lr)])
            for shape in args.shapes for est in known.estimators for lr in known.lrs]
    table = f"sweep-{args.setting}" + (f"-{known.tag}" if known.tag else "")
    path = RESULTS / f"estimator_{table}.json"
    previous = json.loads(path.read_text()) if known.merge and path.is_file() else {}
    if previous and previous.get("seed", args.seed) != args.seed:
        raise SystemExit(f"--merge: {path} was run with seed {previous['seed']}, not {args.seed}")
    reused = dict(previous.get("runs", {}))
    todo = [job for job in jobs if job[0] not in reused]
    if reused:
        print(f"--merge: reusing {len(reused)} records of {path.name}; {len(todo)} of {len(jobs)} runs to do",
              flush=True)
    if not args.collect_only and todo:
        prepare_gt(todo, args)
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        runs = {name: with_dense_loss(r, table) for name, r in reused.items()}

        def job(name: str, shape: str, ov: list[str]) -> dict | None:  # the dense loss in the run's own worker
            return with_dense_loss(run_one(name, shape, SETTINGS[args.setting] + ov + list(args.override), table,
                                           args.device, args.seed, args.threads, args.collect_only, False),
                                   table)

        futures = {name: pool.submit(job, name, shape, ov) for name, shape, ov in todo}
        for name, f in futures.items():  # in submission order: the JSON is rewritten after each finished run
            runs[name] = f.result()
            if runs[name] is not None and known.merge:
                write(path, args, known, previous, runs, reused, "(partial: the sweep is still running)")
    text = write(path, args, known, previous, runs, reused, None)
    print(text)
    if known.curves:
        print("\n" + curves_table(runs))
    print(f"\nwrote {path}")


def validation_curve(run_dir: Path) -> list[list[float]] | None:
    """``[[step, chamfer, hausdorff], ...]`` of the run's validation steps (its TensorBoard ``shape/*``
    scalars, the last write of each step when a run was resumed); ``None`` when the run folder is gone."""
    if not (run_dir / "tb").is_dir():
        return None
    logging.getLogger("tensorboard").setLevel(logging.ERROR)  # a resumed run's purge notice is expected
    events = EventAccumulator(str(run_dir / "tb"), size_guidance={"scalars": 0})
    events.Reload()
    if "shape/chamfer" not in events.Tags()["scalars"]:
        return None
    cd = {e.step: e.value for e in events.Scalars("shape/chamfer")}
    hd = {e.step: e.value for e in events.Scalars("shape/hausdorff")}
    return [[step, cd[step], hd[step]] for step in sorted(cd) if step in hd]


def with_dense_loss(record: dict | None, table: str) -> dict | None:
    """``record`` with ``train_loss_dense`` and ``curve`` (:func:`validation_curve`) added from its run
    folder (each kept when already there or when the folder is gone)."""
    if record is None:
        return record
    run_dir = REPO / "runs" / "bench" / table / record["name"]
    if record.get("curve") is None:
        curve = validation_curve(run_dir)
        record = record if curve is None else {**record, "curve": curve}
    if record.get("train_loss_dense") is not None:
        return record
    loss = dense_train_loss(run_dir)
    return record if loss is None else {**record, "train_loss_dense": loss}


def criterion(rows: list[tuple[float, dict]]) -> str:
    """The selection key: the dense full-training-set loss when every run has it, else ``final_loss``."""
    return "train_loss_dense" if all(r.get("train_loss_dense") is not None for _, r in rows) else "final_loss"


def curves_table(runs: dict) -> str:
    """Markdown: Chamfer (Hausdorff) of every run with a curve at each of its validation steps."""
    rows = [(name, r["curve"]) for name, r in runs.items() if r is not None and r.get("curve")]
    steps = sorted({int(c[0]) for _, curve in rows for c in curve})
    lines = ["| run | " + " | ".join(f"CD (HD) at step {s}" for s in steps) + " |", "|---|" + "---|" * len(steps)]
    for name, curve in rows:
        at = {int(c[0]): c for c in curve}
        lines.append(f"| {name} | " + " | ".join(f"{fmt(at[s][1])} ({fmt(at[s][2])})" if s in at else "–"
                                                  for s in steps) + " |")
    return "\n".join(lines)


def write(path: Path, args, known, previous: dict, runs: dict, reused: dict, note: str | None) -> str:
    """Tabulate ``runs`` (each (shape, estimator)'s rate selected on its training-image loss, never on the
    geometry) and write the JSON; returns the Markdown."""
    lrs = sorted(set(known.lrs) | set(previous.get("lrs", [])))
    shapes = [s for s in SHAPES if s in args.shapes or any(k.startswith(f"{s}-") for k in runs)]
    ests = [e for e in ESTIMATORS if e in known.estimators or any(f"-{e}-lr" in k for k in runs)]
    rates = " / ".join(f"{lr:g}" for lr in lrs)
    lines = [f"| shape | estimator | train loss (dense, all views) at lr {rates} | last-batch loss at lr {rates} | "
             f"Chamfer at lr {rates} | selected lr | Chamfer (selected) | Hausdorff (selected) | "
             f"CD / CD of sampled (selected) | oracle lr (best CD, not a selection) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    best, oracle = {}, {}
    for shape in shapes:
        for est in ests:
            rows = [(lr, runs.get(f"{shape}-{est}-lr{lr:g}")) for lr in lrs]
            done = [(lr, r) for lr, r in rows if r is not None]
            if not done:
                continue
            key = criterion(done)
            lr_sel, sel = min(done, key=lambda t: t[1][key])
            lr_last, _ = min(done, key=lambda t: t[1]["final_loss"])
            lr_orc, orc = min(done, key=lambda t: t[1]["chamfer"])
            lr_worst, _ = max(done, key=lambda t: t[1]["chamfer"])
            best[f"{shape}/{est}"] = dict(lr=lr_sel, criterion=key, lr_by_final_loss=lr_last,
                                          chamfer=sel["chamfer"], hausdorff=sel["hausdorff"],
                                          final_loss=sel["final_loss"], train_loss_dense=sel.get("train_loss_dense"),
                                          selected_worst_chamfer=len(done) > 1 and lr_sel == lr_worst,
                                          complete=len(done) == len(lrs))
            oracle[f"{shape}/{est}"] = dict(lr=lr_orc, chamfer=orc["chamfer"], hausdorff=orc["hausdorff"])
    for shape in shapes:
        ref = best.get(f"{shape}/sampled")
        for est in ests:
            b = best.get(f"{shape}/{est}")
            if b is None:
                lines.append(f"| {shape} | {est} | not run | | | | | | | |")
                continue
            rows = [(lr, runs.get(f"{shape}-{est}-lr{lr:g}")) for lr in lrs]
            dense = " / ".join(f"{r['train_loss_dense']:.4f}" if r and r.get("train_loss_dense") is not None else "–"
                               for _, r in rows)
            last = " / ".join(f"{r['final_loss']:.4f}" if r else "–" for _, r in rows)
            cds = " / ".join(fmt(r["chamfer"]) if r else "–" for _, r in rows)
            mark = "" if b["complete"] else " (of the finished rates)"
            mark += "" if b["criterion"] == "train_loss_dense" else " (on the last-batch loss)"
            ratio = f"{b['chamfer'] / ref['chamfer']:.2f}" if ref else "–"
            o = oracle[f"{shape}/{est}"]
            lines.append(f"| {shape} | {est} | {dense} | {last} | {cds} | {b['lr']:g}{mark} | {fmt(b['chamfer'])} | "
                         f"{fmt(b['hausdorff'])} | {ratio} | {o['lr']:g} ({fmt(o['chamfer'])}) |")
    text = "\n".join(lines)
    overrides = SETTINGS[args.setting] + list(args.override)
    payload = dict(setting=args.setting, tag=known.tag, overrides=overrides, lrs=lrs, seed=args.seed,
                   selection="per (shape, estimator): the lr of the lowest train_loss_dense (L1 of the final scene "
                             "on all training views, dense renderer); final_loss (last step's batch) where a run "
                             "folder is gone. Chamfer is never used to select; 'oracle' is for information only.",
                   selected=best, oracle_best_chamfer=oracle,
                   runs={k: v for k, v in runs.items() if v is not None}, markdown=text)
    if reused:
        old = previous.get("reused_overrides", {})
        payload["reused_overrides"] = {k: old.get(k, previous.get("overrides")) for k in reused}
        payload["reused_overrides"] = {k: v for k, v in payload["reused_overrides"].items() if v != overrides}
        if not payload["reused_overrides"]:
            del payload["reused_overrides"]
    if note:
        payload["note"] = note
    payload["machine"] = machine()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, payload)
    return text


if __name__ == "__main__":
    main()
