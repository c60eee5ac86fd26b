"""Image and adversarial losses of the neural renderer (pix2pix: ``λ_L1·L1 + adversarial``).

The generator (point features + U-Net shader) minimises
``lambda_l1 · ((1 − s)·|I − I*|₁ + s·D-SSIM) + weight · G_adv`` (``s = ssim_weight``, 0 by default: the
pix2pix objective; D-SSIM ``= (1 − SSIM)/2`` with kornia's 11×11 Gaussian window);
the conditional PatchGAN discriminator minimises ``D_adv``. ``mode`` selects the adversarial
objective: ``lsgan`` (least squares, targets 1/0) or ``bce`` (binary cross-entropy on logits).
"""
from __future__ import annotations

from typing import Literal

import kornia
import torch
import torch.nn.functional as F

GanMode = Literal["lsgan", "bce"]


def l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute error between images of equal shape (scalar)."""
    if pred.shape != target.shape:
        raise ValueError(f"pred/target: shapes differ: {list(pred.shape)} vs {list(target.shape)}")
    return (pred - target).abs().mean()


def _target_loss(logits: torch.Tensor, real: bool, mode: GanMode) -> torch.Tensor:
    target = torch.ones_like(logits) if real else torch.zeros_like(logits)
    if mode == "lsgan":
        return F.mse_loss(logits, target)
    if mode == "bce":
        return F.binary_cross_entropy_with_logits(logits, target)
    raise ValueError(f"mode: expected 'lsgan' or 'bce', got {mode!r}")


def generator_adversarial(fake_logits: torch.Tensor, mode: GanMode = "lsgan") -> torch.Tensor:
    """Generator's adversarial loss: make the discriminator call ``fake_logits [B,1,h,w]`` real."""
    return _target_loss(fake_logits, True, mode)


def discriminator_loss(real_logits: torch.Tensor, fake_logits: torch.Tensor,
                       mode: GanMode = "lsgan") -> torch.Tensor:
    """Discriminator loss ``½ (loss(real → 1) + loss(fake → 0))`` on patch logits ``[B,1,h,w]``."""
    return 0.5 * (_target_loss(real_logits, True, mode) + _target_loss(fake_logits, False, mode))


def dssim_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Structural dissimilarity ``(1 − SSIM)/2`` of images ``[B,C,H,W]`` in [0, 1] (mean; 11×11 window)."""
    if pred.shape != target.shape:
        raise ValueError(f"pred/target: shapes differ: {list(pred.shape)} vs {list(target.shape)}")
    return kornia.losses.ssim_loss(pred, target, window_size=11, max_val=1.0)


def generator_loss(pred: torch.Tensor, target: torch.Tensor, fake_logits: torch.Tensor | None, *,
                   lambda_l1: float = 100.0, adv_weight: float = 1.0, ssim_weight: float = 0.0,
                   mode: GanMode = "lsgan") -> dict[str, torch.Tensor]:
    """Total generator loss and its parts.

    Args:
        pred, target: images ``[B, 3, H, W]``.
        fake_logits: discriminator logits on ``pred`` (``None``: no adversarial term).
        lambda_l1: weight of the image term (pix2pix: 100).
        adv_weight: weight of the adversarial term.
        ssim_weight: share ``s`` in [0, 1] of D-SSIM in the image term ``(1 − s)·L1 + s·D-SSIM``.

    Returns:
        ``{"total", "l1"}`` plus ``"dssim"`` when ``ssim_weight > 0`` and ``"adv"`` when
        ``fake_logits`` is given (scalars).
    """
    if not 0.0 <= ssim_weight <= 1.0:
        raise ValueError(f"ssim_weight: expected a value in [0, 1], got {ssim_weight}")
    l1 = l1_loss(pred, target)
    out = {"l1": l1, "total": lambda_l1 * l1}
    if ssim_weight > 0:
        out["dssim"] = dssim_loss(pred, target)
        out["total"] = lambda_l1 * ((1.0 - ssim_weight) * l1 + ssim_weight * out["dssim"])
    if fake_logits is not None:
        adv = generator_adversarial(fake_logits, mode)
        out["adv"] = adv
        out["total"] = out["total"] + adv_weight * adv
    return out
