"""Issue 57's GPU targets and the readers of the measurements they are judged on (used by benchmarks.gpu_targets,
the table `.ci/gpu_check.sh` ends with)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from benchmarks.common import markdown

#: (name, target text, comparison, bound)
TARGETS = [("one-view lego step at 200²", "≤ 8 ms", "le", 8.0),
           ("8 views (200²)", "≤ 20 ms", "le", 20.0),
           ("lego val PSNR within 3 min", "≥ 32.5 dB", "ge", 32.5),
           ("main job", "≤ 20 s", "le", 20.0),
           ("op against gsplat", "≤ 3×", "le", 3.0)]


def read(path: Path | None) -> dict[str, Any] | None:
    """The JSON at ``path`` (``None`` when absent)."""
    if path is None or not path.is_file():
        return None
    return json.loads(path.read_text())


def step_ms(lego: dict[str, Any] | None, views: int) -> float | None:
    """The median step time (ms) of ``views`` views at 200² in ``benchmarks.gpu_lego``'s result."""
    rows = [r for r in (lego or {}).get("rows", []) if r.get("resolution") == 200 and r.get("views") == views]
    return float(rows[0]["step_ms"]) if rows else None


def psnr_within(curve: dict[str, Any] | None, seconds: float) -> float | None:
    """The best val PSNR of a run's curve ``[[s, psnr], ...]`` reached within ``seconds``."""
    pts = [p for s, p in (curve or {}).get("curve", []) if s <= seconds and p is not None]
    return max(pts) if pts else None


def gsplat_ratio(op: dict[str, Any] | None) -> float | None:
    """The largest nsplat / gsplat time ratio of ``benchmarks.op_cuda``'s gsplat rows."""
    rows = [r["nsplat_over_gsplat"] for r in ((op or {}).get("gsplat_2dgs") or {}).get("rows", [])
            if r.get("nsplat_over_gsplat") is not None]
    return max(rows) if rows else None


def evaluate(values: list[float | None]) -> list[dict[str, Any]]:
    """One row per target: its measured value (``None``: not measured) and whether it is met."""
    out = []
    for (name, text, cmp, bound), v in zip(TARGETS, values):
        met = None if v is None else (v <= bound if cmp == "le" else v >= bound)
        out.append({"target": name, "bound": text, "measured": v, "met": met})
    return out


def table(rows: list[dict[str, Any]]) -> str:
    """The Markdown table of :func:`evaluate`'s rows."""
    return markdown(["target", "bound", "measured", "met"],
                    [[r["target"], r["bound"], "not measured" if r["measured"] is None else f"{r['measured']:.2f}",
                      {True: "yes", False: "NO", None: "–"}[r["met"]]] for r in rows])
