"""The refine task's metrics: pose errors and masked PSNR / SSIM of the rendered frames.

The SSIM is scikit-image's map (Gaussian window σ = 1.5, reflected borders) averaged over the frame's mask, not
:func:`nsplat.evaluation.image_metrics.ssim` (the valid region's mean, no mask): the two differ by about 1e-3 on a 64×48
frame, and the refinement figures (docs/results.md) were measured with this one.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from skimage.metrics import structural_similarity

from nsplat.tasks.refine.model import Refiner
from nsplat.tasks.refine.poses import pose_report


def image_metrics(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> tuple[float, float]:
    """Masked PSNR and SSIM of one image ``[H,W,C]`` in [0,1] against ``ref`` (``mask [H,W]``).

    SSIM is scikit-image's (Gaussian window σ = 1.5, data range 1) map averaged over valid pixels.
    """
    a = img.detach().clamp(0, 1).cpu().double().numpy()
    b = ref.detach().cpu().double().numpy()
    m = mask.detach().cpu().numpy().astype(bool)
    mse = float(((a - b) ** 2)[m].mean())
    psnr = 10.0 * math.log10(1.0 / max(mse, 1e-12))
    _, smap = structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                    sigma=1.5, use_sample_covariance=False, full=True)
    return psnr, float(smap.mean(-1)[m].mean())


@torch.no_grad()
def evaluate_state(model: Refiner, seed: int, batch: int) -> tuple[dict[str, Any], torch.Tensor]:
    """Pose errors and masked PSNR/SSIM over all frames; returns ``(metrics, renders [B,H,W,C])``."""
    fr = model.frames
    renders = []
    for s in range(0, len(fr), batch):
        idx = torch.arange(s, min(s + batch, len(fr)), device=fr.images.device)
        renders.append(model(idx, seed)[0])
    img = torch.cat(renders)
    ps, ss = zip(*(image_metrics(img[b], fr.images[b], fr.masks[b]) for b in range(len(fr))))
    out: dict[str, Any] = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)),
                           "points": model.scene.num_points}
    if fr.viewmats_gt is not None:
        V, K = model.camera(torch.arange(len(fr), device=fr.images.device))
        out.update(pose_report(V, fr.viewmats_gt))
        if model.cameras is not None and model.cameras.log_focal is not None:
            out["focal_scale"] = torch.exp(model.cameras.log_focal).tolist()
    return out, img
