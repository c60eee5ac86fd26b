"""A coverage term for the fitter: ``weight · mean |alpha − mask|`` against the views' masks.

With RGBA training images (their alpha is the views' ``masks``) the silhouettes are then fitted directly, not
only through the colour contrast with the background.
"""
from __future__ import annotations

import dataclasses

import torch
from torch import nn

from nsplat.config import ConfigError, require_fields
from nsplat.data.views import PosedViews
from nsplat.fitting.strategy import FitState, Strategy, ViewRender
from nsplat.scene import SurfelScene


@dataclasses.dataclass
class MaskLossConfig:
    """The coverage term (off by default).

    Attributes:
        weight: weight of ``mean |alpha − mask|`` added to each view's L1 image loss; 0: off, > 0 needs views
            with masks.
    """

    weight: float = 0.0

    def __post_init__(self) -> None:
        require_fields(self, weight=">=0")


class MaskLoss(Strategy):
    """The coverage term as a fitter strategy."""

    def __init__(self, cfg: MaskLossConfig) -> None:
        self.cfg = cfg

    def attach(self, scene: SurfelScene, views: PosedViews | None) -> dict[str, nn.Module]:
        if views is not None and views.masks is None:
            raise ConfigError("mask_loss.weight: > 0 needs views with masks (RGBA images); these views have none")
        return {}

    def loss(self, fit: FitState, view: ViewRender) -> torch.Tensor:
        mask = fit.views.masks[view.indices].float()
        return self.cfg.weight * (view.alpha[..., 0] - mask).abs().mean(dim=(1, 2)).sum()
