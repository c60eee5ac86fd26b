"""A fair Table-1 comparison of the gradient estimators: the same learning-rate sweep for each.

Every estimator (``ht``, ``ht-pips``, ``paper``, ``sampled``) is run with each learning rate of ``--lrs``
(the rate of positions, normals, scales and features together) on each shape, at a Table-1 budget
(``--setting`` of ``benchmarks/table1.py``). For each (shape, estimator) the rate is **selected on the final
training image loss** (the images the optimiser sees; the ground-truth geometry is never used to choose),
and the selected run's Chamfer / Hausdorff distances to the ground-truth points are reported.

    python benchmarks/estimator_sweep.py --shapes bunny teapot --jobs 1
    python benchmarks/estimator_sweep.py --setting cpu-long --shapes bunny

Writes ``benchmarks/results/estimator_sweep-<setting>.json`` and prints a Markdown table.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table1 import RESULTS, SETTINGS, common_args, fmt, learning_rate, prepare_gt, run_one  # noqa: E402

ESTIMATORS = ("ht", "ht-pips", "paper", "sampled")


def main() -> None:
    import argparse

    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--lrs", nargs="+", type=float, default=[0.01, 0.03, 0.1])
    extra.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=list(ESTIMATORS))
    known, rest = extra.parse_known_args()
    sys.argv = [sys.argv[0]] + rest
    args = common_args(__doc__.splitlines()[0])
    jobs = [(f"{shape}-{est}-lr{lr:g}", shape, ["render.renderer=splat", f"render.estimator={est}", *learning_rate(lr)])
            for shape in args.shapes for est in known.estimators for lr in known.lrs]
    if not args.collect_only:
        prepare_gt(jobs, args)
    from concurrent.futures import ThreadPoolExecutor

    table = f"sweep-{args.setting}"
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        futures = {name: pool.submit(run_one, name, shape, SETTINGS[args.setting] + ov + list(args.override), table,
                                     args.device, args.seed, args.threads, args.collect_only, False)
                   for name, shape, ov in jobs}
        runs = {name: f.result() for name, f in futures.items()}
    lines = ["| shape | estimator | selected lr | final loss per lr | CD (selected) | HD (selected) | CD per lr |",
             "|---|---|---|---|---|---|---|"]
    best = {}
    for shape in args.shapes:
        for est in known.estimators:
            rows = [(lr, runs.get(f"{shape}-{est}-lr{lr:g}")) for lr in known.lrs]
            done = [(lr, r) for lr, r in rows if r is not None]
            if not done:
                lines.append(f"| {shape} | {est} | not run | | | | |")
                continue
            lr_sel, sel = min(done, key=lambda t: t[1]["final_loss"])
            best[f"{shape}/{est}"] = dict(lr=lr_sel, chamfer=sel["chamfer"], hausdorff=sel["hausdorff"],
                                          final_loss=sel["final_loss"])
            losses = " / ".join(f"{r['final_loss']:.4f}" if r else "–" for _, r in rows)
            cds = " / ".join(fmt(r["chamfer"]) if r else "–" for _, r in rows)
            lines.append(f"| {shape} | {est} | {lr_sel:g} | {losses} | {fmt(sel['chamfer'])} | "
                         f"{fmt(sel['hausdorff'])} | {cds} |")
    text = "\n".join(lines)
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"estimator_sweep-{args.setting}.json"
    path.write_text(json.dumps(dict(setting=args.setting, overrides=SETTINGS[args.setting] + list(args.override),
                                    lrs=known.lrs, seed=args.seed, selected=best,
                                    runs={k: v for k, v in runs.items() if v is not None}, markdown=text), indent=1))
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
