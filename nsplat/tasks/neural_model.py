"""The neural task's stage-2 networks: :class:`NeuralRenderer` (points with learned features → op →
U-Net → RGB), its conditional PatchGAN, and the renderer as a :class:`~nsplat.view_model.ViewModel`.

Used by :mod:`nsplat.tasks.neural` (training, evaluation, checkpoints) and its ``view``.
"""
from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import nn

from nsplat import render as gateway
from nsplat.models import PatchDiscriminator, UNet
from nsplat.render import DRAW_STRIDE
from nsplat.scene import SurfelScene
from nsplat.sh import view_colour
from nsplat.tasks.neural_config import Config
from nsplat.view_model import TrainingCameras, ViewModel


class NeuralRenderer(nn.Module):
    """Points with learned features → splatted feature image → U-Net → RGB.

    Attributes:
        scene: :class:`SurfelScene` with ``C`` feature channels (``C + R`` with ``neural.view_colour``: the
            last ``R = view_rest`` are SH coefficients, :meth:`point_features`).
        unet: the shader; input channels ``C`` (+1 coverage channel with ``alpha_input``).
    """

    def __init__(self, scene: SurfelScene, cfg: Config) -> None:
        super().__init__()
        n = cfg.neural
        self.scene = scene
        self.render_cfg = cfg.render
        self.alpha_input = n.alpha_input
        self.residual = n.residual
        self.view_rest = cfg.view_rest()
        u = n.unet
        self.unet = UNet(self.cond_channels, 3, depth=u.depth, width=u.width, max_width=u.max_width, norm=u.norm,
                         dropout=u.dropout, dropout_layers=u.dropout_layers, upsample=u.upsample,
                         output_range=tuple(u.output_range))
        if self.residual:
            nn.init.zeros_(self.unet.head.weight)
            nn.init.zeros_(self.unet.head.bias)
        # Feature background: the data background in the first three (colour) channels, 0 elsewhere.
        bg = torch.zeros(self.channels, dtype=scene.means.dtype)
        k = min(3, self.channels)
        bg[:k] = torch.tensor(cfg.data.background, dtype=bg.dtype)[:k]
        self.register_buffer("background", bg.to(scene.means.device), persistent=False)

    @property
    def channels(self) -> int:
        """Splatted feature channels ``C``."""
        return self.scene.cfg.channels - self.view_rest

    @property
    def cond_channels(self) -> int:
        """Channels of the feature image the U-Net (and the discriminator) sees."""
        return self.channels + int(self.alpha_input)

    def point_features(self, features: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
        """The ``[N,C]`` features splatted for camera ``viewmat [4,4]`` from the stored ``features [N,C(+R)]``:
        as stored, or with ``view_rest`` the first three replaced by the SH colour seen from that camera
        (:func:`nsplat.sh.view_colour` of the mean colour and the last ``R`` channels)."""
        if not self.view_rest:
            return features
        C = self.channels
        colour = view_colour(torch.cat([features[:, :3], features[:, C:]], 1), self.scene.means, viewmat)
        return torch.cat([colour, features[:, 3:C]], 1)

    def feature_image(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                      seed: int | Sequence[int]) -> torch.Tensor:
        """Splatted features (and coverage) ``[B, C(+1), H, W]`` of cameras ``viewmats [B,4,4]``.

        ``seed``: one op seed for all ``B`` cameras (one op call; with ``view_rest`` one call per camera,
        camera ``b`` with ``seed + b``), or ``B`` seeds, one per camera (one call each: a view's samples then
        do not depend on which other views share its call).
        """
        if not isinstance(seed, int):
            if len(seed) != viewmats.shape[0]:
                raise ValueError(f"seed: expected {viewmats.shape[0]} per-camera seeds, got {len(seed)}")
            return torch.cat([self.feature_image(viewmats[b:b + 1], Ks[b:b + 1], width, height, int(sd))
                              for b, sd in enumerate(seed)])
        s = self.scene
        if self.view_rest and viewmats.shape[0] > 1:  # per-camera colours: one op call per camera, seed + b
            return torch.cat([self.feature_image(viewmats[b:b + 1], Ks[b:b + 1], width, height, seed + b)
                              for b in range(viewmats.shape[0])])
        feats = self.point_features(s.features, viewmats[0])
        out = gateway.render(s.means, s.normals, s.scales, s.opacities, feats, viewmats, Ks, width, height,
                             self.render_cfg, seed=seed, background=self.background)
        img = torch.cat([out.image, out.alpha], -1) if self.alpha_input else out.image
        return img.permute(0, 3, 1, 2).contiguous()

    def forward(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                seed: int | Sequence[int], draws: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rgb [B,3,H,W], feature image [B,C(+1),H,W])``; ``seed`` as in :meth:`feature_image`.

        ``draws``: the feature image is the mean of that many independent op draws (draw ``j`` renders
        with the seeds shifted by ``j·DRAW_STRIDE``; draw 0 is the single-draw render).
        """
        cond = self.feature_image(viewmats, Ks, width, height, seed)
        for j in range(1, draws):
            shifted = seed + j * DRAW_STRIDE if isinstance(seed, int) else [s + j * DRAW_STRIDE for s in seed]
            cond = cond + self.feature_image(viewmats, Ks, width, height, shifted)
        if draws > 1:
            cond = cond / draws
        return self.unet(cond, base=cond[:, :3] if self.residual else None), cond


def build_discriminator(cfg: Config, cond_channels: int) -> PatchDiscriminator | None:
    """The PatchGAN, or ``None`` when ``neural.gan.enabled`` is false (nothing allocated)."""
    g = cfg.neural.gan
    if not g.enabled:
        return None
    return PatchDiscriminator(cond_channels, 3, width=g.width, layers=g.layers, norm=g.norm)


def _eval_unet(model: NeuralRenderer) -> Callable[[torch.Tensor], torch.Tensor]:
    """The U-Net of ``model`` as an eval-mode shader ``[1,C',H,W] → [1,3,H,W]`` (restores the mode after)."""

    def shade(cond: torch.Tensor) -> torch.Tensor:
        was = model.training
        model.eval()
        try:
            return model.unet(cond, base=cond[:, :3] if model.residual else None)
        finally:
            model.train(was)

    return shade


def neural_view(model: NeuralRenderer, cameras: TrainingCameras | None, seed: int = 0) -> ViewModel:
    """``model`` as a view: its features splatted by the op, shaded by its U-Net (eval mode)."""
    s = model.scene
    colours = None
    if model.view_rest:
        def colours(features: torch.Tensor, normals: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
            return model.point_features(features, viewmat[0])[None]

    return ViewModel(s.means, s.normals, s.scales, s.opacities, s.features, model.background, colours=colours,
                     shader=_eval_unet(model), alpha_input=model.alpha_input, render_cfg=model.render_cfg,
                     cameras=cameras, task="neural", seed=seed)
