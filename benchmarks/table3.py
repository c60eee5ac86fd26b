"""Table 3: influence of the number of training views (16, 64, 124, 300) on bunny reconstruction (ht).

``--setting paper``: 300 epochs for every view count, as in the paper (more views → more steps).
``--setting cpu``: the CPU budget of :mod:`benchmarks.table1` held at a **fixed number of optimisation
steps** (that of the 24-view CPU runs: 20 epochs × 24 views / batch 6 = 80 steps), i.e.
``epochs = round(480 / views)`` (at least 1), repositioning about 4 times per run — a fixed-compute
version of the ablation, because 300 views × 20 epochs does not fit the CPU budget. Writes
``benchmarks/results/table3-<setting>.json`` and ``docs/images/reconstruct/ablation_views-<setting>.png``.

    python -m benchmarks.table3 --jobs 2
"""
from __future__ import annotations

from benchmarks.ablation import report
from benchmarks.table1 import common_args, run_all

VIEWS = (16, 64, 124, 300)
#: The paper's Table 3 (HD, CD as printed).
PAPER_TABLE3 = {16: (49.159, 20.138), 64: (1.097, 0.156), 124: (0.442, 0.125), 300: (0.409, 0.13)}
CPU_VIEW_RENDERS = 480  # 20 epochs x 24 views


def overrides(views: int, setting: str) -> list[str]:
    ov = ["render.renderer=splat", "render.estimator=ht", f"data.views={views}"]
    if setting == "cpu":
        epochs = max(1, round(CPU_VIEW_RENDERS / views))
        steps_per_epoch = -(-views // 6)  # the cpu setting's batch of 6
        ov += [f"optim.epochs={epochs}", f"optim.reposition.every={max(1, epochs // 4)}",
               f"log.validate={max(1, epochs // 4) * steps_per_epoch}"]
    return ov


def main() -> None:
    args = common_args(__doc__.splitlines()[0])
    jobs = [(f"bunny-v{v}", "bunny", overrides(v, args.setting)) for v in VIEWS]
    rows = run_all(jobs, "table3", args)
    report("table3", args, VIEWS, rows, PAPER_TABLE3, ("views", "epochs"), ("epochs",), "training views",
           "ablation_views")


if __name__ == "__main__":
    main()
