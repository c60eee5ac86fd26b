"""pix2pix-style U-Net shader: a splatted feature image ``[B, C, H, W]`` → RGB ``[B, 3, H, W]``.

Encoder: a 3×3 stem at full resolution, then ``depth`` stride-2 4×4 convolutions (LeakyReLU 0.2,
normalisation after all but the first), widths doubling from ``width`` up to ``max_width``.
Decoder: mirror image with upsampling (4×4 transposed convolutions as in pix2pix, or bilinear
upsampling + 3×3 convolution), ReLU, normalisation, dropout on the ``dropout_layers`` innermost
decoder levels, and skip connections by concatenation. A 3×3 head maps to ``out_channels`` and a
squashing activation to ``output_range`` (optionally as a residual around a base image). Weights and
activations are channels-last (NHWC); inputs may be in either layout. Inputs of any size are padded
(replicate) to a multiple of ``2**depth`` and the output is cropped back, so ``H, W`` need not be
powers of two.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

Norm = Literal["batch", "instance", "group", "none"]
Upsample = Literal["transpose", "bilinear"]


def norm_layer(kind: Norm, channels: int) -> nn.Module:
    """Normalisation module of ``kind`` for ``channels`` feature maps (``none`` → identity)."""
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "instance":
        return nn.InstanceNorm2d(channels, affine=True)
    if kind == "group":
        return nn.GroupNorm(min(8, channels), channels)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"norm: expected one of batch, instance, group, none; got {kind!r}")


@dataclasses.dataclass
class UNetConfig:
    """The shader's shape (``neural.unet`` of the neural task's config).

    Attributes:
        depth: number of stride-2 levels (the input is padded to a multiple of ``2**depth``), >= 1.
        width: channels after the stem; doubled per level up to ``max_width``.
        max_width: the widest level's channels (>= ``width``).
        norm: ``batch``, ``instance``, ``group`` or ``none``.
        dropout: dropout probability in [0, 1) in the ``dropout_layers`` innermost decoder levels.
        dropout_layers: decoder levels with dropout, counted from the innermost.
        upsample: ``transpose`` (4×4 transposed convolutions, pix2pix) or ``bilinear`` (+ 3×3 convolution; no
            checkerboard artefacts).
        output_range: ``(lo, hi)`` with ``hi > lo``; the output is ``lo + (hi - lo) · sigmoid(x)``.
    """

    depth: int = 4
    width: int = 32
    max_width: int = 128
    norm: Norm = "group"
    dropout: float = 0.0
    dropout_layers: int = 2
    upsample: Upsample = "bilinear"
    output_range: tuple[float, float] = (0.0, 1.0)

    def __post_init__(self) -> None:
        if self.depth < 1:
            raise ValueError(f"depth: expected a value >= 1, got {self.depth}")
        if self.width < 1:
            raise ValueError(f"width: expected a value >= 1, got {self.width}")
        if self.max_width < self.width:
            raise ValueError(f"max_width: expected >= width ({self.width}), got {self.max_width}")
        if self.norm not in ("batch", "instance", "group", "none"):
            raise ValueError(f"norm: expected one of batch, instance, group, none; got {self.norm!r}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout: expected a probability in [0, 1), got {self.dropout}")
        if self.dropout_layers < 0:
            raise ValueError(f"dropout_layers: expected a value >= 0, got {self.dropout_layers}")
        if self.upsample not in ("transpose", "bilinear"):
            raise ValueError(f"upsample: expected 'transpose' or 'bilinear', got {self.upsample!r}")
        lo, hi = (float(v) for v in self.output_range)
        if not hi > lo:
            raise ValueError(f"output_range: expected (lo, hi) with hi > lo, got {self.output_range}")


class UNet(nn.Module):
    """U-Net shader.

    Args:
        in_channels: feature channels ``C`` of the input image.
        out_channels: output channels (3 for RGB).
        cfg: the network's shape (:class:`UNetConfig`; default: its defaults).
    """

    def __init__(self, in_channels: int, out_channels: int = 3, cfg: UNetConfig | None = None) -> None:
        super().__init__()
        cfg = UNetConfig() if cfg is None else cfg
        if in_channels < 1 or out_channels < 1:
            raise ValueError(f"in_channels/out_channels: expected >= 1, got {in_channels}/{out_channels}")
        depth, width, max_width, norm = cfg.depth, cfg.width, cfg.max_width, cfg.norm
        dropout, dropout_layers, upsample = cfg.dropout, cfg.dropout_layers, cfg.upsample
        lo, hi = (float(v) for v in cfg.output_range)
        self.depth = depth
        self.register_buffer("_range", torch.tensor([lo, hi]), persistent=False)
        widths = [min(width * 2**i, max_width) for i in range(depth + 1)]
        self.stem = nn.Sequential(nn.Conv2d(in_channels, widths[0], 3, padding=1), nn.LeakyReLU(0.2, True))
        self.down = nn.ModuleList()
        for i in range(depth):
            layers: list[nn.Module] = [nn.Conv2d(widths[i], widths[i + 1], 4, stride=2, padding=1)]
            if i + 1 < depth:  # pix2pix: no normalisation at the 1×1-ish bottleneck
                layers.append(norm_layer(norm, widths[i + 1]))
            layers.append(nn.LeakyReLU(0.2, True))
            self.down.append(nn.Sequential(*layers))
        self.up = nn.ModuleList()
        for i in reversed(range(depth)):
            c_in = widths[i + 1] if i == depth - 1 else 2 * widths[i + 1]
            if upsample == "transpose":
                layers = [nn.ConvTranspose2d(c_in, widths[i], 4, stride=2, padding=1)]
            else:
                layers = [nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
                          nn.Conv2d(c_in, widths[i], 3, padding=1)]
            layers += [norm_layer(norm, widths[i]), nn.ReLU(True)]
            if dropout > 0 and (depth - 1 - i) < dropout_layers:
                layers.append(nn.Dropout(dropout))
            self.up.append(nn.Sequential(*layers))
        self.head = nn.Conv2d(2 * widths[0], out_channels, 3, padding=1)
        # channels-last (NHWC) weights and activations: oneDNN's faster CPU convolutions with group norm
        # (docs/performance.md, "Network precision"); the input is converted in forward.
        self.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor, base: torch.Tensor | None = None) -> torch.Tensor:
        """``x [B, C, H, W]`` → ``[B, out_channels, H, W]`` in ``output_range``.

        With ``base [B, out_channels, H, W]`` (values in ``output_range``) the network predicts a
        residual in logit space: ``lo + (hi - lo)·sigmoid(logit((base - lo)/(hi - lo)) + head)``,
        so a zero head reproduces ``base``.
        """
        if x.dim() != 4:
            raise ValueError(f"x: expected shape [B, C, H, W], got {list(x.shape)}")
        H, W = x.shape[-2:]
        m = 2**self.depth
        ph, pw = (-H) % m, (-W) % m
        if ph or pw:
            x = F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2), mode="replicate")
        skips = [self.stem(x.contiguous(memory_format=torch.channels_last))]
        for layer in self.down:
            skips.append(layer(skips[-1]))
        h = skips.pop()
        for layer in self.up:
            h = torch.cat([layer(h), skips.pop()], dim=1)
        out = self.head(h)
        if ph or pw:
            out = out[..., ph // 2: ph // 2 + H, pw // 2: pw // 2 + W]
        lo, hi = self._range[0], self._range[1]
        if base is not None:
            if base.shape != out.shape:
                raise ValueError(f"base: expected shape {list(out.shape)}, got {list(base.shape)}")
            b = ((base - lo) / (hi - lo)).clamp(1e-3, 1.0 - 1e-3)
            out = out + torch.log(b) - torch.log1p(-b)
        return lo + (hi - lo) * torch.sigmoid(out)
