"""Table 2: influence of the per-pixel sample count m (1, 3, 5, 20, 40) on bunny reconstruction (estimator ht).

Same harness and settings as :mod:`benchmarks.table1` (``--setting``). Prints a Markdown
table beside the paper's numbers, writes ``benchmarks/results/table2-<setting>.json`` and the plot
``docs/images/reconstruct/ablation_samples-<setting>.png``.

    python -m benchmarks.table2 --jobs 2
"""
from __future__ import annotations

from benchmarks.ablation import report
from benchmarks.table1 import REPO, SETTINGS, common_args, run_all
from nsplat.config import load_config, read_yaml
from nsplat.tasks.reconstruct import Config

SAMPLES = (1, 3, 5, 20, 40)
#: The paper's Table 2 (HD, CD as printed).
PAPER_TABLE2 = {1: (8.287, 6.766), 3: (8.87, 3.532), 5: (8.189, 2.717), 20: (1.07, 0.105), 40: (0.442, 0.125)}


def main() -> None:
    args = common_args(__doc__.splitlines()[0])
    jobs = [(f"bunny-m{m}", "bunny", ["render.renderer=splat", "render.estimator=ht", f"render.samples={m}"])
            for m in SAMPLES]
    # Table 1's bunny/ht run is this table's row at the setting's own m (same config): reuse it rather than recompute.
    cfg = load_config(Config, read_yaml(REPO / "configs" / "reconstruct_bunny.yaml"),
                      SETTINGS[args.setting] + list(args.override))
    shared = REPO / "runs" / "bench" / f"table1-{args.setting}" / "bunny-ht"
    mine = REPO / "runs" / "bench" / f"table2-{args.setting}" / f"bunny-m{cfg.render.samples}"
    reusable = cfg.render.samples in SAMPLES and (shared / "metrics.json").is_file()
    if reusable and not mine.exists() and not args.override:
        mine.parent.mkdir(parents=True, exist_ok=True)
        mine.symlink_to(shared, target_is_directory=True)
    rows = run_all(jobs, "table2", args)
    report("table2", args, SAMPLES, rows, PAPER_TABLE2, ("m",), (), "samples per pixel m", "ablation_samples")


if __name__ == "__main__":
    main()
