"""Evaluation protocols of held-out views: which images the metrics are computed on, and how.

* ``standard`` (the published NeRF-synthetic and Mip-NeRF 360 tables: 3D Gaussian splatting's
  ``metrics.py``, nerfbaselines): the render and the ground truth, both composited on the background,
  are quantised to 8 bits (:func:`nsplat.evaluation.image_metrics.quantise`, as writing and reading PNGs does); then
  PSNR, SSIM over zero-padded images (:func:`nsplat.evaluation.image_metrics.ssim_zero_padded`) and LPIPS with the
  VGG backbone (3DGS's metrics) and the AlexNet one (gsplat's trainer, nerfbaselines), each when it runs
  offline (:func:`nsplat.evaluation.image_metrics.lpips_status`; otherwise a one-line note in its place).
* ``nsplat`` (this project's figures before the protocol existed): the float render against the float
  ground truth, PSNR and SSIM over the valid region (:func:`nsplat.evaluation.image_metrics.ssim`), LPIPS likewise.

:func:`score_views` computes the per-view scores, :func:`summary` the ``metrics.json`` entries and
:func:`write_per_view_csv` / :func:`read_per_view_csv` the per-view table (one row per view: name, PSNR,
SSIM and each available LPIPS).
"""
from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Sequence

import torch

from nsplat.evaluation.image_metrics import LPIPS_BACKBONES, lpips, lpips_status, psnr, quantise, ssim, ssim_zero_padded

PROTOCOLS = ("standard", "nsplat")


@dataclasses.dataclass
class Scores:
    """Per-view scores of ``B`` views under one protocol.

    Attributes:
        protocol: ``standard`` or ``nsplat``.
        per_view: metric name (``psnr``, ``ssim``, ``lpips_vgg``, ``lpips_alex``) → ``[B]`` float64, in
            that order; an LPIPS backbone that cannot run is absent.
        notes: ``lpips_<net>`` → the one-line reason it is absent.
    """

    protocol: str
    per_view: dict[str, torch.Tensor]
    notes: dict[str, str]


def protocol_images(rgb: torch.Tensor, gt: torch.Tensor, protocol: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The images ``[B,H,W,3]`` the metrics of ``protocol`` see: quantised to 8 bits (``standard``) or as
    they are (``nsplat``)."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"eval.protocol: expected one of {list(PROTOCOLS)}, got {protocol!r}")
    if protocol == "standard":
        return quantise(rgb), quantise(gt)
    return rgb, gt


def score_views(rgb: torch.Tensor, gt: torch.Tensor, protocol: str) -> Scores:
    """Scores of renders ``rgb [B,H,W,3]`` against ``gt [B,H,W,3]`` (both in [0, 1], on the background)."""
    a, b = protocol_images(rgb, gt, protocol)
    per_view = {"psnr": psnr(a, b), "ssim": ssim_zero_padded(a, b) if protocol == "standard" else ssim(a, b)}
    notes = {}
    for net in LPIPS_BACKBONES:
        ok, msg = lpips_status(net)
        if ok:
            per_view[f"lpips_{net}"] = lpips(a, b, net=net).double().cpu()
        else:
            notes[f"lpips_{net}"] = msg
    return Scores(protocol, {k: v.double().cpu() for k, v in per_view.items()}, notes)


def _stats(x: torch.Tensor) -> dict[str, float]:
    return {"mean": float(x.mean()), "std": float(x.std(unbiased=False)) if x.numel() > 1 else 0.0}


def summary(scores: Scores) -> dict:
    """``metrics.json`` entries: ``protocol``, ``psnr`` and ``ssim`` (mean, std over views) and ``lpips``:
    per backbone its mean and std, or the note saying why it was skipped."""
    lp = {net: (_stats(scores.per_view[f"lpips_{net}"]) if f"lpips_{net}" in scores.per_view
                else scores.notes[f"lpips_{net}"]) for net in LPIPS_BACKBONES}
    return {"protocol": scores.protocol, "psnr": _stats(scores.per_view["psnr"]),
            "ssim": _stats(scores.per_view["ssim"]), "lpips": lp}


def summary_text(scores: Scores) -> str:
    """``PSNR 31.99 ± 1.90 dB, SSIM 0.9875 ± 0.0055, LPIPS vgg 0.0123, alex 0.0101`` (or ``LPIPS skipped: ...``)."""
    s = summary(scores)
    text = (f"PSNR {s['psnr']['mean']:.2f} ± {s['psnr']['std']:.2f} dB, "
            f"SSIM {s['ssim']['mean']:.4f} ± {s['ssim']['std']:.4f}")
    have = [f"{net} {v['mean']:.4f}" for net, v in s["lpips"].items() if isinstance(v, dict)]
    notes = sorted({v for v in s["lpips"].values() if isinstance(v, str)})
    return f"{text}, LPIPS {', '.join(have + notes)}"


def write_per_view_csv(path: Path, names: Sequence[str], scores: Scores) -> Path:
    """One row per view (``name`` and every per-view score, written exactly: ``repr`` of the float)."""
    keys = list(scores.per_view)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", *keys])
        for i, name in enumerate(names):
            w.writerow([name, *(repr(float(scores.per_view[k][i])) for k in keys)])
    return path


def read_per_view_csv(path: Path) -> list[dict[str, str | float]]:
    """The rows of a :func:`write_per_view_csv` file: ``name`` (str) and the scores (float)."""
    with open(path, newline="") as fh:
        return [{k: (v if k == "name" else float(v)) for k, v in row.items()} for row in csv.DictReader(fh)]
