"""Conditional PatchGAN discriminator (pix2pix): judges overlapping patches of (condition, image).

Input: the condition (the splatted feature image, ``[B, C, H, W]``) concatenated with an RGB image
(``[B, 3, H, W]``). ``layers`` stride-2 4×4 convolutions (LeakyReLU 0.2, normalisation after all but
the first), one stride-1 4×4 convolution and a 1-channel 4×4 output: one logit per patch
(receptive field 70 px for ``layers = 3``). Patch logits are unbounded; the loss decides between
LSGAN and BCE (:mod:`nsplat.models.losses`).
"""
from __future__ import annotations

import dataclasses

import torch
from torch import nn

from .unet import Norm, norm_layer


@dataclasses.dataclass
class PatchGANConfig:
    """The discriminator's shape (the ``neural.gan`` section of the neural task's config extends it).

    Attributes:
        width: channels of the first layer, doubled per layer up to ``8 · width``.
        layers: number of stride-2 convolutions (receptive field 70 px for 3).
        norm: ``batch``, ``instance``, ``group`` or ``none``.
    """

    width: int = 32
    layers: int = 3
    norm: Norm = "instance"

    def __post_init__(self) -> None:
        if self.width < 1:
            raise ValueError(f"width: expected a value >= 1, got {self.width}")
        if self.layers < 1:
            raise ValueError(f"layers: expected a value >= 1, got {self.layers}")
        if self.norm not in ("batch", "instance", "group", "none"):
            raise ValueError(f"norm: expected one of batch, instance, group, none; got {self.norm!r}")


class PatchDiscriminator(nn.Module):
    """Conditional PatchGAN.

    Args:
        cond_channels: channels of the condition (feature image).
        image_channels: channels of the judged image (3).
        cfg: the discriminator's shape (:class:`PatchGANConfig`; default: its defaults).
    """

    def __init__(self, cond_channels: int, image_channels: int = 3, cfg: PatchGANConfig | None = None) -> None:
        super().__init__()
        cfg = PatchGANConfig() if cfg is None else cfg
        if cond_channels < 0 or image_channels < 1:
            raise ValueError(f"cond_channels/image_channels: expected >= 0 / >= 1, got "
                             f"{cond_channels}/{image_channels}")
        width, layers, norm = cfg.width, cfg.layers, cfg.norm
        self.in_channels = cond_channels + image_channels
        mods: list[nn.Module] = [nn.Conv2d(self.in_channels, width, 4, stride=2, padding=1),
                                 nn.LeakyReLU(0.2, True)]
        c = width
        for i in range(1, layers + 1):
            c_next = min(width * 2**i, width * 8)
            stride = 2 if i < layers else 1
            mods += [nn.Conv2d(c, c_next, 4, stride=stride, padding=1), norm_layer(norm, c_next),
                     nn.LeakyReLU(0.2, True)]
            c = c_next
        mods.append(nn.Conv2d(c, 1, 4, stride=1, padding=1))
        self.net = nn.Sequential(*mods)
        self.layers = layers

    def min_size(self) -> int:
        """Smallest image side (pixels) that yields at least one patch: ``3 · 2**layers``."""
        return 3 * 2**self.layers

    def forward(self, cond: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """Patch logits ``[B, 1, h, w]`` for ``cond [B, C, H, W]`` and ``image [B, 3, H, W]``."""
        if cond.shape[0] != image.shape[0] or cond.shape[-2:] != image.shape[-2:]:
            raise ValueError(f"cond/image: batch and spatial sizes must match, got {list(cond.shape)} "
                             f"and {list(image.shape)}")
        if min(image.shape[-2:]) < self.min_size():
            raise ValueError(f"image: sides must be >= {self.min_size()} px for a {self.layers}-layer "
                             f"PatchGAN, got {list(image.shape[-2:])}")
        x = torch.cat([cond, image], dim=1)
        if x.shape[1] != self.in_channels:
            raise ValueError(f"cond/image: expected {self.in_channels} channels together, got {x.shape[1]}")
        return self.net(x)
