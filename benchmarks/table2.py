"""Table 2: influence of the per-pixel sample count m (1, 3, 5, 20, 40) on bunny reconstruction (estimator ht).

Same harness and settings as ``benchmarks/table1.py`` (``--setting cpu|paper``). Prints a Markdown
table beside the paper's numbers, writes ``benchmarks/results/table2-<setting>.json`` and the plot
``docs/images/reconstruct/ablation_samples-<setting>.png``.

    python benchmarks/table2.py --jobs 2
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from table1 import IMAGES, REPO, common_args, fmt, run_all, write_json  # noqa: E402

SAMPLES = (1, 3, 5, 20, 40)
#: The paper's Table 2 (HD, CD as printed).
PAPER_TABLE2 = {1: (8.287, 6.766), 3: (8.87, 3.532), 5: (8.189, 2.717), 20: (1.07, 0.105), 40: (0.442, 0.125)}


def plot(x: list[int], rows: list[dict], xlabel: str, path, logx: bool = False) -> None:
    """Two log-log panels (Chamfer, Hausdorff; both definitions) of ``rows`` against ``x``; nothing
    is drawn when fewer than two runs have finished."""
    if len(rows) < 2:
        return
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    for ax, key in zip(axes, ("chamfer", "hausdorff")):
        ax.plot(x, [r[key] for r in rows], "o-", label=f"{key} (plain)")
        ax.plot(x, [r[f"{key}_sq"] for r in rows], "s--", label=f"{key}² (authors)")
        ax.set_xlabel(xlabel)
        ax.set_yscale("log")
        if logx:
            ax.set_xscale("log")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main() -> None:
    args = common_args(__doc__.splitlines()[0])
    jobs = [(f"bunny-m{m}", "bunny", ["render.renderer=splat", "render.estimator=ht", f"render.samples={m}"])
            for m in SAMPLES]
    # m = 40 with ht is exactly Table 1's bunny/ht run (same config): reuse it rather than recompute.
    shared = REPO / "runs" / "bench" / f"table1-{args.setting}" / "bunny-ht"
    mine = REPO / "runs" / "bench" / f"table2-{args.setting}" / "bunny-m40"
    if (shared / "metrics.json").is_file() and not mine.exists() and not args.override:
        mine.parent.mkdir(parents=True, exist_ok=True)
        mine.symlink_to(shared, target_is_directory=True)
    rows = run_all(jobs, "table2", args)
    done = [(x, r) for x, r in zip(SAMPLES, rows) if r is not None]
    lines = ["| m | HD (plain) | CD (plain) | HD² (authors) | CD² (authors) | paper HD | paper CD | time s |",
             "|---|---|---|---|---|---|---|---|"]
    for m, r in zip(SAMPLES, rows):
        if r is None:
            lines.append(f"| {m} | not run | | | | {PAPER_TABLE2[m][0]} | {PAPER_TABLE2[m][1]} | |")
            continue
        lines.append(f"| {m} | {fmt(r['hausdorff'])} | {fmt(r['chamfer'])} | {fmt(r['hausdorff_sq'])} | "
                     f"{fmt(r['chamfer_sq'])} | {PAPER_TABLE2[m][0]} | {PAPER_TABLE2[m][1]} | {r['wall_s']:.0f} |")
    table = "\n".join(lines)
    print(table)
    plot([x for x, _ in done], [r for _, r in done], "samples per pixel m", IMAGES / f"ablation_samples-{args.setting}.png", logx=True)
    print(f"\nwrote {write_json('table2', args, [r for _, r in done], {'paper': PAPER_TABLE2, 'markdown': table})}")


if __name__ == "__main__":
    main()
