"""The table and plot code shared by the ablations :mod:`benchmarks.table2` (samples per pixel) and
:mod:`benchmarks.table3` (training views): one Markdown row per setting beside the paper's numbers,
the two-panel plot and the JSON result."""
from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure

from benchmarks.table1 import IMAGES, fmt, write_json

METRICS_HEADER = "HD (plain) | CD (plain) | HD² (authors) | CD² (authors) | paper HD | paper CD | time s"


def plot(x: list[int], rows: list[dict], xlabel: str, path: Path, logx: bool = False) -> None:
    """Two log-log panels (Chamfer, Hausdorff; both definitions) of ``rows`` against ``x``; nothing
    is drawn when fewer than two runs have finished."""
    if len(rows) < 2:
        return
    fig = Figure(figsize=(8, 3.2))
    axes = fig.subplots(1, 2)
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


def markdown(xs: tuple[int, ...], rows: list[dict | None], paper: dict[int, tuple[float, float]],
             columns: tuple[str, ...], extra: tuple[str, ...] = ()) -> str:
    """The ablation table: per setting ``x`` the ``columns`` label cells (``x``, then ``rows[i][e]`` for
    ``e`` in ``extra``), the run's distances, the paper's (HD, CD) and the wall time; "not run" rows keep
    the paper's numbers."""
    cols = len(columns) + 7
    lines = ["| " + " | ".join(columns) + " | " + METRICS_HEADER + " |", "|" + "---|" * cols]
    for x, r in zip(xs, rows):
        hd, cd = paper[x]
        if r is None:
            lines.append(f"| {x} | " + "| " * len(extra) + f"not run | | | | {hd} | {cd} | |")
            continue
        cells = [str(x), *(str(r[e]) for e in extra), fmt(r["hausdorff"]), fmt(r["chamfer"]), fmt(r["hausdorff_sq"]),
                 fmt(r["chamfer_sq"]), str(hd), str(cd), f"{r['wall_s']:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def report(name: str, args, xs: tuple[int, ...], rows: list[dict | None], paper: dict[int, tuple[float, float]],  # noqa: ANN001
           columns: tuple[str, ...], extra: tuple[str, ...], xlabel: str, image: str) -> None:
    """Print the table, draw ``IMAGES/<image>-<setting>.png`` and write ``results/<name>-<setting>.json``."""
    done = [(x, r) for x, r in zip(xs, rows) if r is not None]
    table = markdown(xs, rows, paper, columns, extra)
    print(table)
    plot([x for x, _ in done], [r for _, r in done], xlabel, IMAGES / f"{image}-{args.setting}.png", logx=True)
    write_json(name, args, [r for _, r in done], {'paper': paper, 'markdown': table})
