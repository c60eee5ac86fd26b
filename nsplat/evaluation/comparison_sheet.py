"""A comparison sheet of held-out views: one PNG with a row per view, ground truth | render | error heat map.

The heat map is the per-pixel mean absolute RGB error on a fixed scale (0 black to :data:`ERROR_MAX` yellow,
matplotlib's ``inferno``), so that sheets of different runs compare at a glance. Drawn with matplotlib's
object API (no pyplot, no display).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

#: Mean absolute RGB error shown at the top of the heat map's scale.
ERROR_MAX = 0.2
#: Smallest side of a panel on the sheet in pixels (small images are enlarged, nearest neighbour).
MIN_PANEL = 192


def spread(count: int, views: int) -> list[int]:
    """Indices of at most ``views`` of ``count`` views, evenly spread, first and last included."""
    if views >= count:
        return list(range(count))
    return sorted({round(i * (count - 1) / max(views - 1, 1)) for i in range(views)})


def write_sheet(path: Path, names: Sequence[str], gt: torch.Tensor, rgb: torch.Tensor, psnr: torch.Tensor,
                views: int) -> Path:
    """Write the sheet of at most ``views`` of the ``B`` views (evenly spread) to ``path``.

    Args:
        names: ``B`` view names. gt, rgb: ``[B,H,W,3]`` in [0, 1] (the images the metrics saw).
        psnr: ``[B]`` per-view PSNR (dB), printed beside each row.
    """
    rows = spread(len(names), views)
    H, W = gt.shape[1:3]
    scale = max(1.0, MIN_PANEL / min(H, W))
    dpi = 100
    fig = Figure(figsize=(3 * W * scale / dpi + 0.4, len(rows) * (H * scale / dpi + 0.3) + 0.3), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(rows), 3, squeeze=False)
    error = (rgb.double() - gt.double()).abs().mean(-1)
    for r, i in enumerate(rows):
        panels = [(gt[i], "ground truth"), (rgb[i], f"render, {float(psnr[i]):.2f} dB"),
                  (error[i], f"|error| (0 to {ERROR_MAX:g})")]
        for c, (img, title) in enumerate(panels):
            ax = axes[r][c]
            data = img.detach().float().cpu().numpy()
            if data.ndim == 2:
                ax.imshow(data, cmap="inferno", vmin=0.0, vmax=ERROR_MAX, interpolation="nearest")
            else:
                ax.imshow(np.clip(data, 0.0, 1.0), interpolation="nearest")
            ax.set_title(f"{Path(names[i]).name}: {title}" if c == 0 else title, fontsize=8)
            ax.set_axis_off()
    fig.tight_layout(pad=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path
