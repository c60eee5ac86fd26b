"""Image and adversarial losses of the neural renderer (pix2pix: ``λ_L1·L1 + adversarial``).

The generator (point features + U-Net shader) minimises ``lambda_l1 · |I − I*|₁ + weight · G_adv``;
the conditional PatchGAN discriminator minimises ``D_adv``. ``mode`` selects the adversarial
objective: ``lsgan`` (least squares, targets 1/0) or ``bce`` (binary cross-entropy on logits).
"""
from __future__ import annotations

from typing import Literal

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


def generator_loss(pred: torch.Tensor, target: torch.Tensor, fake_logits: torch.Tensor | None, *,
                   lambda_l1: float = 100.0, adv_weight: float = 1.0,
                   mode: GanMode = "lsgan") -> dict[str, torch.Tensor]:
    """Total generator loss and its parts.

    Args:
        pred, target: images ``[B, 3, H, W]``.
        fake_logits: discriminator logits on ``pred`` (``None``: L1 only).
        lambda_l1: weight of the L1 term (pix2pix: 100).
        adv_weight: weight of the adversarial term.

    Returns:
        ``{"total", "l1"}`` plus ``"adv"`` when ``fake_logits`` is given (scalars).
    """
    l1 = l1_loss(pred, target)
    out = {"l1": l1, "total": lambda_l1 * l1}
    if fake_logits is not None:
        adv = generator_adversarial(fake_logits, mode)
        out["adv"] = adv
        out["total"] = out["total"] + adv_weight * adv
    return out
