"""The neural task's stage-2 model: the points with learned features (:func:`neural_scene_from` the stage-1
surfels), :class:`NeuralRenderer` (points → op → U-Net → RGB), its conditional PatchGAN, the trained model
from a checkpoint (:func:`load_model`; a point-only run's stage 1 as a :class:`PointRenderer`) and the
renderer as a :class:`~nsplat.render.view_model.ViewModel`.
"""
from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import nn

from nsplat.models import PatchDiscriminator, UNet
from nsplat.render import renderer as gateway
from nsplat.render.renderer import DRAW_STRIDE
from nsplat.render.sh import view_colour
from nsplat.render.view_model import TrainingCameras, ViewModel
from nsplat.run.checkpoint import load_checkpoint
from nsplat.run.context import RunContext, RunFolderError
from nsplat.run.engine import checkpoint_rows
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.tasks.neural import precision
from nsplat.tasks.neural.capture import with_capture_render
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.starts import geometry_scene_config


def neural_scene_config(cfg: Config) -> SceneConfig:
    """Stage-2 scene: ``C`` raw features (+ stage 1's higher SH coefficients with ``neural.view_colour``);
    learnable attributes from ``neural.learn``."""
    return SceneConfig(channels=cfg.neural.features + cfg.view_rest(), learn=list(cfg.neural.learn),
                       opacity=cfg.geometry.opacity, scale=None, feature_activation="identity")


@torch.no_grad()
def neural_scene_from(cfg: Config, geo: SurfelScene, seed: int) -> SurfelScene:
    """Stage-2 scene from the stage-1 surfels: geometry copied, features = [colour, N(0, σ²)…] (with
    ``neural.view_colour``: followed by stage 1's higher SH coefficients).

    Points with opacity below ``geometry.prune_opacity`` are dropped.
    """
    keep = torch.ones(geo.num_points, dtype=torch.bool, device=geo.means.device)
    if cfg.geometry.opacity is None:
        keep = geo.opacities >= cfg.geometry.prune_opacity
        if not bool(keep.any()):
            raise RuntimeError("stage 1 left no point above geometry.prune_opacity")
    C = cfg.neural.features
    gen = torch.Generator().manual_seed(seed)
    feats = torch.randn(int(keep.sum()), C, generator=gen, dtype=geo.means.dtype) * cfg.neural.feature_init_std
    feats = feats.to(geo.means.device)
    k = min(3, C)
    feats[:, :k] = geo.features[keep][:, :k]
    if cfg.view_rest():
        feats = torch.cat([feats, geo.features[keep][:, 3:]], 1)
    scfg = neural_scene_config(cfg)
    kwargs = {"features": feats}
    if scfg.opacity is None:
        kwargs["opacities"] = geo.opacities[keep]
    return SurfelScene.from_points(scfg, geo.means[keep].clone(), geo.normals[keep].clone(),
                                   scales=geo.scales[keep].clone(), **kwargs)


class NeuralRenderer(nn.Module):
    """Points with learned features → splatted feature image → U-Net → RGB.

    Attributes:
        scene: :class:`SurfelScene` with ``C`` feature channels (``C + R`` with ``neural.view_colour``: the
            last ``R = view_rest`` are SH coefficients, :meth:`point_features`).
        unet: the shader; input channels ``C`` (+1 coverage channel with ``alpha_input``).
        compute_dtype: the networks' compute precision (``neural.precision`` resolved on the scene's device at
            construction, :func:`nsplat.tasks.neural.precision.resolve`): the U-Net in :meth:`shade` and the
            discriminator
            in training run under :func:`nsplat.tasks.neural.precision.autocast` of it.
    """

    def __init__(self, scene: SurfelScene, cfg: Config) -> None:
        super().__init__()
        n = cfg.neural
        self.scene = scene
        self.render_cfg = cfg.render
        self.alpha_input = n.alpha_input
        self.residual = n.residual
        self.view_rest = cfg.view_rest()
        self.compute_dtype = precision.resolve(n.precision, scene.means.device)
        self.unet = UNet(self.cond_channels, 3, n.unet)
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
        (:func:`nsplat.render.sh.view_colour` of the mean colour and the last ``R`` channels)."""
        if not self.view_rest:
            return features
        C = self.channels
        colour = view_colour(torch.cat([features[:, :3], features[:, C:]], 1), self.scene.means, viewmat)
        return torch.cat([colour, features[:, 3:C]], 1)

    def feature_image(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                      seed: int | Sequence[int]) -> torch.Tensor:
        """Splatted features (and coverage) ``[B, C(+1), H, W]`` of cameras ``viewmats [B,4,4]``, in one op call.

        ``seed``: one op seed for all ``B`` cameras, or ``B`` seeds, one per camera: camera ``b`` samples as the
        only camera of a call with seed ``seed[b]`` (op.md §3), so a view's samples do not depend on which other
        views share its call. With ``view_rest`` each camera sees its own point features (per-camera features
        ``[B,N,C]``) and one seed means ``seed + b`` for camera ``b`` (the truncated renderer, which takes one
        feature tensor for all cameras: one call per camera).
        """
        B = viewmats.shape[0]
        per_camera = self.view_rest and B > 1
        if not isinstance(seed, int):
            if len(seed) != B:
                raise ValueError(f"seed: expected {B} per-camera seeds, got {len(seed)}")
            seed = torch.tensor([int(sd) for sd in seed], dtype=torch.int64)
        elif per_camera:
            seed = torch.tensor([seed + b for b in range(B)], dtype=torch.int64)
        if per_camera and self.render_cfg.renderer == "truncated":
            return torch.cat([self.feature_image(viewmats[b:b + 1], Ks[b:b + 1], width, height, int(seed[b]))
                              for b in range(B)])
        s = self.scene
        if per_camera:
            feats = torch.stack([self.point_features(s.features, viewmats[b]) for b in range(B)])
        else:
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
        return self.shade(cond), cond

    def shade(self, cond: torch.Tensor) -> torch.Tensor:
        """The U-Net on the feature image ``cond [B,C',H,W]`` (float32) in :attr:`compute_dtype`: RGB
        ``[B,3,H,W]`` in float32."""
        with precision.autocast(self.compute_dtype, cond.device.type):
            rgb = self.unet(cond, base=cond[:, :3] if self.residual else None)
        return rgb.float()


def build_discriminator(cfg: Config, cond_channels: int) -> PatchDiscriminator | None:
    """The PatchGAN, or ``None`` when ``neural.gan.enabled`` is false (nothing allocated)."""
    g = cfg.neural.gan
    if not g.enabled:
        return None
    return PatchDiscriminator(cond_channels, 3, g)


def _eval_unet(model: NeuralRenderer) -> Callable[[torch.Tensor], torch.Tensor]:
    """The U-Net of ``model`` as an eval-mode shader ``[1,C',H,W] → [1,3,H,W]`` (restores the mode after)."""

    def shade(cond: torch.Tensor) -> torch.Tensor:
        was = model.training
        model.eval()
        try:
            return model.shade(cond)
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


class PointRenderer(nn.Module):
    """The point-only model (``neural.steps: 0``): stage 1's surfels with their colour (RGB, or SH seen from
    each camera) splatted by the op, behind :class:`NeuralRenderer`'s interface for evaluation and videos.

    Attributes:
        scene: the stage-1 :class:`SurfelScene` (``geometry.ply``). shading: ``geometry.optim.shading``.
    """

    def __init__(self, scene: SurfelScene, cfg: Config) -> None:
        super().__init__()
        self.scene = scene
        self.render_cfg = cfg.render
        self.shading = cfg.geometry.optim.shading
        bg = torch.tensor(cfg.data.background, dtype=scene.means.dtype, device=scene.means.device)
        self.register_buffer("background", bg, persistent=False)

    def forward(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, seed: int,
                draws: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rgb [B,3,H,W], rgb [B,3,H,W])`` of cameras ``viewmats [B,4,4]``, ``Ks [B,3,3]`` (camera ``b`` with
        op seed ``seed + b`` where the colour is per camera; the mean of ``draws`` op draws), as
        :func:`nsplat.render.renderer.render_views` renders stage 1 alone; the image is also the "feature image"."""
        img = gateway.render_views(self.scene, viewmats, Ks, width, height, self.render_cfg, seed=seed,
                                   shading=self.shading, background=self.background, draws=draws)
        rgb = img.permute(0, 3, 1, 2).contiguous()
        return rgb, rgb


#: What evaluation and videos render: the stage-2 model or, for a point-only run, stage 1.
Renderer = NeuralRenderer | PointRenderer


def load_model(cfg: Config, ctx: RunContext) -> Renderer:
    """The trained renderer from the run's latest checkpoint (the state ``neural.select`` picks); with
    ``neural.steps: 0`` the point-only model
    from the run's ``geometry.ply`` (:class:`PointRenderer`)."""
    cfg = with_capture_render(cfg)
    if cfg.neural.steps == 0:
        path = ctx.run_dir / "geometry.ply"
        if not path.is_file():
            raise RunFolderError(f"--run {ctx.run_dir}: no geometry.ply yet (stage 1 has not finished)")
        return PointRenderer(SurfelScene.load_ply(path, geometry_scene_config(cfg), device=ctx.device), cfg)
    payload = load_checkpoint(ctx.run_dir, map_location="cpu")
    points = checkpoint_rows(payload, "model", "scene._means")
    model = NeuralRenderer(SurfelScene(neural_scene_config(cfg), points, device=ctx.device), cfg).to(ctx.device)
    best = payload["extra"].get("best_val") if cfg.neural.select == "best_val" else None
    model.load_state_dict(payload["modules"]["model"] if best is None else best["state"])
    return model
