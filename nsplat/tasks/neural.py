"""Task ``neural``: neural point rendering (paper §4 "Neural Rendering") on NeRF-synthetic scenes.

Stage 1 (geometry): RGB surfels either read from a PLY or initialised on the visual hull of the
training silhouettes (:mod:`nsplat.data.visual_hull`) and fitted to the training views with the op
(:func:`nsplat.fitting.fit`, L1, features = RGB, no shading); written to ``geometry.ply``.

Stage 2 (neural): every point gets ``C`` learned features (the first three start from its stage-1
colour); the op splats them (plus coverage; the background is the data background in the colour
channels and 0 elsewhere) into a feature image that a U-Net shader
(:class:`nsplat.models.UNet`) turns into RGB, trained with ``λ_L1·L1 + adversarial`` against a
conditional PatchGAN (:class:`nsplat.models.PatchDiscriminator`). Which point attributes stay
learnable, with their own learning rates, is ``neural.learn``.

Run folder: ``config.yaml``, ``geometry/`` (stage-1 logs and checkpoints), ``geometry.ply``,
``tb/`` (TensorBoard), ``checkpoints/`` (stage 2, atomic, exact resume), ``history.json`` (train
and val PSNR over steps), ``eval_<split>/`` (``metrics.json``, ``per_view.json``, PNGs) and
``orbit.mp4``.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Literal

import imageio
import imageio.v3 as iio
import numpy as np
import torch
from torch import nn
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from nsplat.cameras import look_at
from nsplat.checkpoint import CheckpointError, NoCheckpoint, load_checkpoint, save_checkpoint
from nsplat.config import ConfigError, require_fields
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.views import PosedViews
from nsplat.data.procedural import ProceduralSpec, ensure_scene
from nsplat.data.visual_hull import hull_points
from nsplat.losses import discriminator_loss, generator_loss
from nsplat.metrics_image import lpips, lpips_status, psnr, ssim
from nsplat.models import PatchDiscriminator, UNet
from nsplat.fitting import FitConfig, fit
from nsplat import render as gateway
from nsplat.render import RenderConfig
from nsplat.runctx import RunContext
from nsplat.scene import ATTRIBUTES, SceneConfig, SurfelScene
from nsplat.viewer import live
from nsplat.viewer.runs import cameras_of, neural_view

log = logging.getLogger(__name__)
REPO_ROOT = Path(__file__).resolve().parents[2]
#: Op seeds: stage-2 step ``k`` uses ``seed·STRIDE + STAGE2_OFFSET + k``, evaluation ``seed·STRIDE + EVAL_OFFSET``
#: (disjoint from stage 1's ``seed·10⁶ + step·batch + j`` in :func:`nsplat.fitting.fit` for any run length).
_SEED_STRIDE, _STAGE2_OFFSET, _EVAL_OFFSET = 1_000_000_000, 500_000_000, 900_000_000


# ---------------------------------------------------------------------------------------------- config
@dataclasses.dataclass
class ProceduralConfig:
    """The embedded procedural scene (:class:`nsplat.data.ProceduralSpec`), generated on first use.

    Attributes:
        seed: scene seed. resolution: rendered image side (px). views: (train, val, test) counts.
        objects: number of objects. cache_dir: where scenes are generated (relative: to the repo root).
    """

    seed: int = 0
    resolution: int = 64
    views: tuple[int, int, int] = (40, 8, 8)
    objects: int = 4
    cache_dir: str = "data_cache"

    def __post_init__(self) -> None:
        require_fields(self, resolution=">=1", views=">=1", objects=">=1")


@dataclasses.dataclass
class DataConfig:
    """Where the posed images come from.

    Attributes:
        source: ``procedural`` (the embedded scene) or ``nerf_synthetic`` (a folder at ``root``).
        root: NeRF-synthetic scene folder (relative paths: to the repo root).
        resolution: image side after resizing (``null``: as stored).
        background: RGB composited under the RGBA images (white: NeRF's evaluation protocol).
        train_limit, val_limit, test_limit: use only the first k frames of a split (``null``: all).
    """

    source: Literal["procedural", "nerf_synthetic"] = "procedural"
    root: str | None = None
    resolution: int | None = None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    procedural: ProceduralConfig = dataclasses.field(default_factory=ProceduralConfig)
    train_limit: int | None = None
    val_limit: int | None = None
    test_limit: int | None = None

    def __post_init__(self) -> None:
        if self.source == "nerf_synthetic" and not self.root:
            raise ConfigError("data.root: required when data.source is nerf_synthetic")
        if self.resolution is not None and self.resolution < 8:
            raise ConfigError(f"data.resolution: expected >= 8 pixels or null, got {self.resolution}")
        if any(not 0.0 <= c <= 1.0 for c in self.background):
            raise ConfigError(f"data.background: expected RGB values in [0, 1], got {list(self.background)}")


@dataclasses.dataclass
class GeometryFitConfig(FitConfig):
    """:class:`nsplat.fitting.FitConfig` with this stage's defaults (short CPU schedule, RGB
    features rendered without shading: photographs carry their own)."""

    epochs: int = 8
    batch: int = 4
    lr: float = 0.01
    lrs: dict[str, float] = dataclasses.field(default_factory=lambda: {
        "means": 0.002, "normals": 0.01, "scales": 0.005, "opacities": 0.05, "features": 0.05})
    lr_decays: int = 2
    shading: Literal["none"] = "none"
    reposition_every: int = 4


@dataclasses.dataclass
class GeometryConfig:
    """Stage 1: RGB surfels fitted to the training views.

    Attributes:
        init: ``hull`` (visual hull of the training silhouettes) or ``ply`` (a PLY written by
            :meth:`nsplat.scene.SurfelScene.save_ply` with this stage's attributes, e.g. a previous
            run's ``geometry.ply``).
        ply: path of that PLY (relative: to the repo root).
        bbox: visual-hull bounds ``(xmin, ymin, zmin, xmax, ymax, zmax)``.
        grid: visual-hull voxels per side. alpha_threshold, dilate, min_seen: see
            :func:`nsplat.data.visual_hull.carve`. max_points: cap on the initial point count.
        scale_factor: initial surfel std-dev in units of the mean 3-NN spacing.
        opacity: constant opacity (nothing allocated) or ``null`` for learned per-point opacities.
        init_opacity: initial per-point opacity.
        learn: attributes fitted in this stage (rates in ``optim.lrs``).
        optim: :class:`GeometryFitConfig` (``epochs: 0`` keeps the initial points).
        prune_opacity: points whose opacity ends below this are dropped before stage 2.
    """

    init: Literal["hull", "ply"] = "hull"
    ply: str | None = None
    bbox: tuple[float, float, float, float, float, float] = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
    grid: int = 64
    alpha_threshold: float = 0.5
    dilate: int = 1
    min_seen: float = 0.5
    max_points: int = 20000
    scale_factor: float = 1.0
    opacity: float | None = None
    init_opacity: float = 0.9
    learn: list[str] = dataclasses.field(default_factory=lambda: ["means", "normals", "scales", "opacities",
                                                                  "features"])
    optim: GeometryFitConfig = dataclasses.field(default_factory=GeometryFitConfig)
    prune_opacity: float = 0.02

    def __post_init__(self) -> None:
        if self.init == "ply" and not self.ply:
            raise ConfigError("geometry.ply: required when geometry.init is ply")
        if self.grid < 8:
            raise ConfigError(f"geometry.grid: expected >= 8, got {self.grid}")
        if self.max_points < 1:
            raise ConfigError(f"geometry.max_points: expected >= 1, got {self.max_points}")
        if not 0.0 < self.init_opacity < 1.0:
            raise ConfigError(f"geometry.init_opacity: expected a value in (0, 1), got {self.init_opacity}")
        bad = [a for a in self.learn if a not in ATTRIBUTES]
        if bad:
            raise ConfigError(f"geometry.learn: unknown attribute(s) {bad}; expected a subset of {list(ATTRIBUTES)}")
        if self.opacity is not None and "opacities" in self.learn:
            raise ConfigError("geometry.learn: 'opacities' needs geometry.opacity: null (per-point opacities)")


@dataclasses.dataclass
class UNetConfig:
    """Shader network (:class:`nsplat.models.UNet`)."""

    depth: int = 4
    width: int = 32
    max_width: int = 128
    norm: Literal["batch", "instance", "group", "none"] = "group"
    dropout: float = 0.0
    dropout_layers: int = 2
    upsample: Literal["transpose", "bilinear"] = "bilinear"
    output_range: tuple[float, float] = (0.0, 1.0)


@dataclasses.dataclass
class GanConfig:
    """Conditional PatchGAN (:class:`nsplat.models.PatchDiscriminator`) and the adversarial loss.

    Attributes:
        enabled: train with the adversarial term (``false``: L1 only; no discriminator is built).
        mode: ``lsgan`` or ``bce``. weight: adversarial weight (pix2pix: 1). lambda_l1: L1 weight (100).
        lr, betas: discriminator Adam. width, layers, norm: discriminator shape.
        start: step of stage 2 at which the adversarial term starts (the L1 term alone before).
    """

    enabled: bool = True
    mode: Literal["lsgan", "bce"] = "lsgan"
    weight: float = 1.0
    lambda_l1: float = 100.0
    lr: float = 2e-4
    betas: tuple[float, float] = (0.5, 0.999)
    width: int = 32
    layers: int = 3
    norm: Literal["batch", "instance", "group", "none"] = "instance"
    start: int = 0


@dataclasses.dataclass
class NeuralConfig:
    """Stage 2: learned point features + U-Net shader (+ PatchGAN).

    Attributes:
        steps: optimisation steps. batch: training views per step.
        features: feature channels C per point.
        feature_init_std: std-dev of the random initial features beyond the first three (colour).
        alpha_input: feed the splatted coverage to the U-Net as an extra channel.
        residual: the U-Net predicts a residual (in logit space, zero-initialised head) around the
            first three splatted feature channels, which start as the stage-1 colours composited on
            the data background; so stage 2 starts from the stage-1 render.
        learn: learnable point attributes → learning rate (others are frozen buffers).
        lr: U-Net learning rate. betas: its Adam decay rates.
        lr_final: every learning rate decays exponentially to this fraction at the last step.
        unet, gan: the networks.
    """

    steps: int = 400
    batch: int = 4
    features: int = 16
    feature_init_std: float = 0.1
    alpha_input: bool = True
    residual: bool = True
    learn: dict[str, float] = dataclasses.field(default_factory=lambda: {"features": 0.01, "means": 1e-4,
                                                                         "opacities": 0.01})
    lr: float = 1e-3
    betas: tuple[float, float] = (0.5, 0.999)
    lr_final: float = 0.1
    unet: UNetConfig = dataclasses.field(default_factory=UNetConfig)
    gan: GanConfig = dataclasses.field(default_factory=GanConfig)

    def __post_init__(self) -> None:
        for key in ("steps", "batch", "features"):
            if getattr(self, key) < 1:
                raise ConfigError(f"neural.{key}: expected >= 1, got {getattr(self, key)}")
        if self.residual and self.features < 3:
            raise ConfigError(f"neural.residual: needs neural.features >= 3, got {self.features}")
        bad = [a for a in self.learn if a not in ATTRIBUTES]
        if bad:
            raise ConfigError(f"neural.learn: unknown attribute(s) {bad}; expected a subset of {list(ATTRIBUTES)}")
        if not 0.0 < self.lr_final <= 1.0:
            raise ConfigError(f"neural.lr_final: expected a fraction in (0, 1], got {self.lr_final}")


@dataclasses.dataclass
class LogConfig:
    """Logging cadence (in stage-2 steps).

    Attributes:
        every: scalars. images: image summaries. checkpoint: checkpoints (the last step always).
        validate: train-vs-val PSNR (``history.json``; 0 disables). val_views: views per split there.
        progress: show tqdm bars.
    """

    every: int = 10
    images: int = 100
    checkpoint: int = 100
    validate: int = 100
    val_views: int = 8
    progress: bool = True


@dataclasses.dataclass
class EvalConfig:
    """Evaluation and rendering.

    Attributes:
        split: held-out split evaluated at the end of training (and by ``eval`` by default).
        images: write rendered/GT PNGs. orbit_frames, fps: the ``render`` command's orbit video.
    """

    split: Literal["train", "val", "test"] = "test"
    images: bool = True
    orbit_frames: int = 60
    fps: int = 20


@dataclasses.dataclass
class Config:
    """Task ``neural`` (see the module docstring)."""

    task: str = "neural"
    seed: int = 0
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    neural: NeuralConfig = dataclasses.field(default_factory=NeuralConfig)
    log: LogConfig = dataclasses.field(default_factory=LogConfig)
    eval: EvalConfig = dataclasses.field(default_factory=EvalConfig)

    def __post_init__(self) -> None:
        if self.task != "neural":
            raise ConfigError(f"task: expected 'neural', got {self.task!r}")
        if self.seed < 0:
            raise ConfigError(f"seed: expected >= 0, got {self.seed}")
        if "opacities" in self.neural.learn and self.geometry.opacity is not None:
            raise ConfigError("neural.learn: 'opacities' needs geometry.opacity: null (per-point opacities)")


# ---------------------------------------------------------------------------------------------- data
def _path(p: str) -> Path:
    q = Path(p).expanduser()
    return q if q.is_absolute() else REPO_ROOT / q


def scene_root(cfg: Config) -> Path:
    """Folder of the NeRF-synthetic-format scene (the procedural one is generated on first use)."""
    d = cfg.data
    if d.source == "nerf_synthetic":
        root = _path(d.root or "")
        if not (root / "transforms_train.json").is_file():
            raise ConfigError(f"data.root: no transforms_train.json in {root}")
        return root
    p = d.procedural
    spec = ProceduralSpec(seed=p.seed, resolution=p.resolution, views=tuple(p.views), objects=p.objects)
    return ensure_scene(spec, _path(p.cache_dir))


def load_views(cfg: Config, split: str, device: torch.device) -> PosedViews:
    """One split of the configured scene on ``device``."""
    limit = {"train": cfg.data.train_limit, "val": cfg.data.val_limit, "test": cfg.data.test_limit}[split]
    views = load_split(scene_root(cfg), split, resolution=cfg.data.resolution, background=cfg.data.background,
                       limit=limit)
    return views.to(device)


# ---------------------------------------------------------------------------------------------- model
def geometry_scene_config(cfg: Config) -> SceneConfig:
    """Stage-1 scene: RGB colour (sigmoid) and the stage's learnable attributes."""
    g = cfg.geometry
    return SceneConfig(channels=3, learn=list(g.learn), opacity=g.opacity, scale=None,
                       feature_activation="sigmoid")


def neural_scene_config(cfg: Config) -> SceneConfig:
    """Stage-2 scene: ``C`` raw features; learnable attributes from ``neural.learn``."""
    return SceneConfig(channels=cfg.neural.features, learn=list(cfg.neural.learn), opacity=cfg.geometry.opacity,
                       scale=None, feature_activation="identity")


class NeuralRenderer(nn.Module):
    """Points with learned features → splatted feature image → U-Net → RGB.

    Attributes:
        scene: :class:`SurfelScene` with ``C`` feature channels.
        unet: the shader; input channels ``C`` (+1 coverage channel with ``alpha_input``).
    """

    def __init__(self, scene: SurfelScene, cfg: Config) -> None:
        super().__init__()
        n = cfg.neural
        self.scene = scene
        self.render_cfg = cfg.render
        self.alpha_input = n.alpha_input
        self.residual = n.residual
        u = n.unet
        self.unet = UNet(self.cond_channels, 3, depth=u.depth, width=u.width, max_width=u.max_width, norm=u.norm,
                         dropout=u.dropout, dropout_layers=u.dropout_layers, upsample=u.upsample,
                         output_range=tuple(u.output_range))
        if self.residual:
            nn.init.zeros_(self.unet.head.weight)
            nn.init.zeros_(self.unet.head.bias)
        # Feature background: the data background in the first three (colour) channels, 0 elsewhere.
        bg = torch.zeros(scene.cfg.channels, dtype=scene.means.dtype)
        k = min(3, scene.cfg.channels)
        bg[:k] = torch.tensor(cfg.data.background, dtype=bg.dtype)[:k]
        self.register_buffer("background", bg.to(scene.means.device), persistent=False)

    @property
    def cond_channels(self) -> int:
        """Channels of the feature image the U-Net (and the discriminator) sees."""
        return self.scene.cfg.channels + int(self.alpha_input)

    def feature_image(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                      seed: int) -> torch.Tensor:
        """Splatted features (and coverage) ``[B, C(+1), H, W]`` of cameras ``viewmats [B,4,4]``."""
        s = self.scene
        out = gateway.render(s.means, s.normals, s.scales, s.opacities, s.features, viewmats, Ks, width, height,
                             self.render_cfg, seed=seed, background=self.background)
        img = torch.cat([out.image, out.alpha], -1) if self.alpha_input else out.image
        return img.permute(0, 3, 1, 2).contiguous()

    def forward(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rgb [B,3,H,W], feature image [B,C(+1),H,W])``."""
        cond = self.feature_image(viewmats, Ks, width, height, seed)
        return self.unet(cond, base=cond[:, :3] if self.residual else None), cond


def build_discriminator(cfg: Config, cond_channels: int) -> PatchDiscriminator | None:
    """The PatchGAN, or ``None`` when ``neural.gan.enabled`` is false (nothing allocated)."""
    g = cfg.neural.gan
    if not g.enabled:
        return None
    return PatchDiscriminator(cond_channels, 3, width=g.width, layers=g.layers, norm=g.norm)


# ---------------------------------------------------------------------------------------------- stage 1
def _initial_geometry(cfg: Config, train: PosedViews, seed: int) -> SurfelScene:
    g = cfg.geometry
    scfg = geometry_scene_config(cfg)
    device = train.images.device
    if g.init == "ply":
        return SurfelScene.load_ply(_path(g.ply or ""), scfg, device=device)
    hp = hull_points(train.to("cpu"), tuple(g.bbox), g.grid, alpha_threshold=g.alpha_threshold, dilate=g.dilate,
                     min_seen=g.min_seen, max_points=g.max_points, seed=seed)
    log.info("visual hull: %d surface points (voxel %.4f)", hp.means.shape[0], hp.voxel)
    return SurfelScene.from_points(scfg, hp.means.to(device), hp.normals.to(device),
                                   opacities=g.init_opacity if g.opacity is None else None,
                                   features=hp.colours.clamp(0.02, 0.98).to(device), scale_factor=g.scale_factor)


def fit_geometry(cfg: Config, ctx: RunContext, train: PosedViews) -> SurfelScene:
    """Stage 1: initial points, fitted to ``train`` with the op (resumable); writes ``geometry.ply``."""
    scene = _initial_geometry(cfg, train, ctx.seed)
    if cfg.geometry.optim.epochs > 0:
        fit(scene, train.images, train.viewmats, train.Ks, cfg.geometry.optim, cfg.render, ctx.run_dir / "geometry",
            seed=ctx.seed, resume=ctx.resume, background=train.background, progress=cfg.log.progress)
    scene.save_ply(ctx.run_dir / "geometry.ply")
    return scene


@torch.no_grad()
def neural_scene_from(cfg: Config, geo: SurfelScene, seed: int) -> SurfelScene:
    """Stage-2 scene from the stage-1 surfels: geometry copied, features = [colour, N(0, σ²)…].

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
    scfg = neural_scene_config(cfg)
    kwargs = {"features": feats}
    if scfg.opacity is None:
        kwargs["opacities"] = geo.opacities[keep]
    return SurfelScene.from_points(scfg, geo.means[keep].clone(), geo.normals[keep].clone(),
                                   scales=geo.scales[keep].clone(), **kwargs)


# ---------------------------------------------------------------------------------------------- stage 2
@dataclasses.dataclass
class Trainer:
    """Everything stage 2 optimises and checkpoints."""

    model: NeuralRenderer
    disc: PatchDiscriminator | None
    opt_g: torch.optim.Optimizer
    opt_d: torch.optim.Optimizer | None
    sched_g: torch.optim.lr_scheduler.LRScheduler
    sched_d: torch.optim.lr_scheduler.LRScheduler | None
    generator: torch.Generator
    seed: int = 0
    step: int = 0
    history: list = dataclasses.field(default_factory=list)
    elapsed: float = 0.0

    def state(self) -> dict:
        """Checkpoint payload (the scene's point count is implied by its tensors)."""
        st = {"model": self.model.state_dict(), "opt_g": self.opt_g.state_dict(), "sched_g": self.sched_g.state_dict(),
              "generator": self.generator.get_state(), "seed": self.seed, "history": self.history,
              "elapsed": self.elapsed}
        if self.disc is not None:
            st.update(disc=self.disc.state_dict(), opt_d=self.opt_d.state_dict(), sched_d=self.sched_d.state_dict())
        return st

    def load(self, st: dict) -> None:
        """Restore :meth:`state` (after :func:`load_checkpoint` restored the RNGs)."""
        self.model.load_state_dict(st["model"])
        self.opt_g.load_state_dict(st["opt_g"])
        self.sched_g.load_state_dict(st["sched_g"])
        self.generator.set_state(st["generator"])
        self.seed = int(st["seed"])  # a resumed run keeps its seed whatever --seed says now
        self.history, self.elapsed, self.step = list(st["history"]), float(st["elapsed"]), int(st["step"])
        if self.disc is not None:
            if "disc" not in st:
                raise CheckpointError("checkpoint has no discriminator but neural.gan.enabled is true")
            self.disc.load_state_dict(st["disc"])
            self.opt_d.load_state_dict(st["opt_d"])
            self.sched_d.load_state_dict(st["sched_d"])


def make_trainer(cfg: Config, scene: SurfelScene, device: torch.device, seed: int = 0) -> Trainer:
    """Networks, optimisers (Adam) and exponential schedulers for stage 2; ``seed`` drives the
    batch order and the op's per-step seeds."""
    n = cfg.neural
    model = NeuralRenderer(scene, cfg).to(device)
    groups = scene.param_groups(n.learn) + [{"params": list(model.unet.parameters()), "lr": n.lr, "name": "unet"}]
    opt_g = torch.optim.Adam(groups, betas=tuple(n.betas))
    gamma = n.lr_final ** (1.0 / max(1, n.steps))
    sched_g = torch.optim.lr_scheduler.ExponentialLR(opt_g, gamma)
    disc = build_discriminator(cfg, model.cond_channels)
    opt_d = sched_d = None
    if disc is not None:
        disc = disc.to(device)
        opt_d = torch.optim.Adam(disc.parameters(), lr=n.gan.lr, betas=tuple(n.gan.betas))
        sched_d = torch.optim.lr_scheduler.ExponentialLR(opt_d, gamma)
    gen = torch.Generator().manual_seed(seed)
    return Trainer(model, disc, opt_g, opt_d, sched_g, sched_d, gen, seed)


def _nchw(x: torch.Tensor) -> torch.Tensor:
    return x.permute(0, 3, 1, 2).contiguous()


def train_step(cfg: Config, tr: Trainer, train: PosedViews) -> dict[str, float]:
    """One stage-2 step on a random batch of training views; returns scalar losses."""
    n = cfg.neural
    idx = torch.randperm(len(train), generator=tr.generator)[:n.batch].to(train.images.device)
    gt = _nchw(train.images[idx])
    rgb, cond = tr.model(train.viewmats[idx], train.Ks[idx], train.width, train.height, op_seed(tr.seed, tr.step))
    use_gan = tr.disc is not None and tr.step >= n.gan.start
    out: dict[str, float] = {}
    if use_gan:
        tr.opt_d.zero_grad(set_to_none=True)
        c = cond.detach()
        d_loss = discriminator_loss(tr.disc(c, gt), tr.disc(c, rgb.detach()), n.gan.mode)
        d_loss.backward()
        tr.opt_d.step()
        out["loss/disc"] = d_loss.item()
    tr.opt_g.zero_grad(set_to_none=True)
    fake = tr.disc(cond, rgb) if use_gan else None
    losses = generator_loss(rgb, gt, fake, lambda_l1=n.gan.lambda_l1, adv_weight=n.gan.weight, mode=n.gan.mode)
    losses["total"].backward()
    tr.opt_g.step()
    tr.sched_g.step()
    if tr.sched_d is not None:
        tr.sched_d.step()
    out.update({f"loss/{k}": v.item() for k, v in losses.items()})
    out["psnr/train_batch"] = float(psnr(rgb.detach(), gt).mean())
    return out


def op_seed(seed: int, step: int) -> int:
    """Op seed of stage-2 step ``step`` of a run seeded ``seed`` (differs per step so samples differ)."""
    return seed * _SEED_STRIDE + _STAGE2_OFFSET + step


def eval_seed(cfg: Config) -> int:
    """Op seed of every evaluation render (validation, test, orbit): fixed by the config's seed."""
    return cfg.seed * _SEED_STRIDE + _EVAL_OFFSET


@torch.no_grad()
def render_split(model: NeuralRenderer, views: PosedViews, seed: int, batch: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendered RGB ``[B,H,W,3]`` and feature images ``[B,C',H,W]`` of all ``views`` (eval mode)."""
    was = model.training
    model.eval()
    rgbs, conds = [], []
    try:
        for s in range(0, len(views), batch):
            rgb, cond = model(views.viewmats[s:s + batch], views.Ks[s:s + batch], views.width, views.height, seed + s)
            rgbs.append(rgb.permute(0, 2, 3, 1))
            conds.append(cond)
    finally:
        model.train(was)
    return torch.cat(rgbs).clamp(0, 1), torch.cat(conds)


def _preview(cond: torch.Tensor) -> torch.Tensor:
    """First three feature channels, min-max normalised per image, ``[B,3,H,W]``."""
    x = cond[:, :3]
    lo = x.flatten(1).min(1).values[:, None, None, None]
    hi = x.flatten(1).max(1).values[:, None, None, None]
    return (x - lo) / (hi - lo).clamp_min(1e-8)


def train_neural(cfg: Config, ctx: RunContext, scene: SurfelScene | None, train: PosedViews, val: PosedViews | None,
                 state: dict | None = None) -> Trainer:
    """Stage 2 from ``scene`` (fresh) or from a checkpoint ``state`` (resume); returns the trainer."""
    n, lg = cfg.neural, cfg.log
    if state is not None:
        count = state["model"]["scene._means"].shape[0]
        scene = SurfelScene(neural_scene_config(cfg), count, device=ctx.device)
    assert scene is not None
    tr = make_trainer(cfg, scene, ctx.device, ctx.seed)
    if state is not None:
        tr.load(state)
        log.info("resumed stage 2 at step %d", tr.step)
    writer = SummaryWriter(str(ctx.run_dir / "tb"), purge_step=tr.step or None)
    tr_sub = train.spread(lg.val_views)
    val_sub = val.spread(lg.val_views) if val is not None else None
    bar = tqdm(total=n.steps, initial=tr.step, desc="neural", dynamic_ncols=True, disable=not lg.progress)
    cams = cameras_of(train.images, train.viewmats, train.Ks)
    try:
        while tr.step < n.steps:
            t0 = time.perf_counter()
            scalars = train_step(cfg, tr, train)
            dt = time.perf_counter() - t0
            tr.elapsed += dt
            tr.step += 1
            bar.update(1)
            bar.set_postfix(l1=f"{scalars['loss/l1']:.4f}", psnr=f"{scalars['psnr/train_batch']:.2f}")
            live.step(tr.step, lambda: neural_view(tr.model, cams, eval_seed(cfg)))
            last = tr.step == n.steps
            if tr.step % lg.every == 0 or last:
                for k, v in scalars.items():
                    writer.add_scalar(k, v, tr.step)
                for g in tr.opt_g.param_groups:
                    writer.add_scalar(f"lr/{g['name']}", g["lr"], tr.step)
                writer.add_scalar("points", scene.num_points, tr.step)
                writer.add_scalar("time/step_s", dt, tr.step)
            if lg.validate and (tr.step % lg.validate == 0 or last):
                rec = {"step": tr.step, "elapsed_s": tr.elapsed}
                for name, sub in (("train", tr_sub), ("val", val_sub)):
                    if sub is None:
                        continue
                    rgb, _ = render_split(tr.model, sub, seed=eval_seed(cfg))
                    rec[f"{name}_psnr"] = float(psnr(rgb, sub.images).mean())
                    writer.add_scalar(f"psnr/{name}", rec[f"{name}_psnr"], tr.step)
                tr.history.append(rec)
                log.debug("step %d: %s", tr.step, rec)
            if lg.images and (tr.step % lg.images == 0 or last):
                sub = val_sub if val_sub is not None else tr_sub
                rgb, cond = render_split(tr.model, sub.spread(2), seed=eval_seed(cfg))
                gt = sub.spread(2).images
                writer.add_images("images/features", _preview(cond), tr.step)
                writer.add_images("images/render", _nchw(rgb), tr.step)
                writer.add_images("images/gt", _nchw(gt), tr.step)
                writer.add_images("images/error", _nchw((rgb - gt).abs().mean(-1, keepdim=True)), tr.step)
            if tr.step % lg.checkpoint == 0 or last:
                save_checkpoint(ctx.run_dir, tr.step, tr.state())
                _write_json(ctx.run_dir / "history.json", {"history": tr.history, "train_seconds": tr.elapsed})
    finally:
        bar.close()
        writer.close()
    return tr


# ---------------------------------------------------------------------------------------------- commands
def run(cfg: Config, ctx: RunContext) -> dict:
    """Train (stage 1, then stage 2; resumable) and evaluate the held-out split."""
    torch.manual_seed(ctx.seed)
    t0 = time.perf_counter()
    train = load_views(cfg, "train", ctx.device)
    val = load_views(cfg, "val", ctx.device) if cfg.log.validate else None
    state = None
    if ctx.resume:
        try:
            state = load_checkpoint(ctx.run_dir, map_location="cpu")
        except NoCheckpoint:
            state = None
    timing = {}
    if state is None:
        geo = fit_geometry(cfg, ctx, train)
        timing["geometry_s"] = time.perf_counter() - t0
        scene = neural_scene_from(cfg, geo, seed=ctx.seed)
        log.info("stage 2: %d points, %d features", scene.num_points, cfg.neural.features)
        tr = train_neural(cfg, ctx, scene, train, val)
    else:
        tr = train_neural(cfg, ctx, None, train, val, state)
    timing["train_total_s"] = time.perf_counter() - t0
    metrics = evaluate(cfg, ctx, cfg.eval.split, model=tr.model)
    _write_json(ctx.run_dir / "timing.json", {**timing, "neural_steps_s": tr.elapsed})
    return metrics


def load_model(cfg: Config, ctx: RunContext) -> NeuralRenderer:
    """The trained renderer from the run's latest checkpoint."""
    state = load_checkpoint(ctx.run_dir, map_location="cpu")
    count = state["model"]["scene._means"].shape[0]
    model = NeuralRenderer(SurfelScene(neural_scene_config(cfg), count, device=ctx.device), cfg).to(ctx.device)
    model.load_state_dict(state["model"])
    return model


def _write_json(path: Path, obj: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=1))
    os.replace(tmp, path)


def _stats(x: torch.Tensor) -> dict[str, float]:
    x = x.double()
    return {"mean": float(x.mean()), "std": float(x.std(unbiased=False)) if x.numel() > 1 else 0.0}


def _png(x: torch.Tensor) -> np.ndarray:
    return (x.detach().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def evaluate(cfg: Config, ctx: RunContext, split: str = "test", model: NeuralRenderer | None = None) -> dict:
    """PSNR/SSIM (LPIPS if available offline) per view of ``split`` on the configured background.

    Writes ``eval_<split>/metrics.json`` (mean ± std), ``per_view.json`` and ``<name>.png`` /
    ``<name>_gt.png`` per view; logs the means. Returns the metrics dict.
    """
    if split not in ("train", "val", "test"):
        raise ConfigError(f"--split: expected train, val or test, got {split!r}")
    model = model if model is not None else load_model(cfg, ctx)
    views = load_views(cfg, split, ctx.device)
    t0 = time.perf_counter()
    rgb, _ = render_split(model, views, seed=eval_seed(cfg))
    seconds = time.perf_counter() - t0
    p, s = psnr(rgb, views.images), ssim(rgb, views.images)
    ok, lp_msg = lpips_status()
    lp = lpips(rgb, views.images) if ok else None
    out_dir = ctx.run_dir / f"eval_{split}"
    out_dir.mkdir(parents=True, exist_ok=True)
    per_view = []
    for i, name in enumerate(views.names):
        stem = Path(name).name
        row = {"name": name, "psnr": float(p[i]), "ssim": float(s[i])}
        if lp is not None:
            row["lpips"] = float(lp[i])
        per_view.append(row)
        if cfg.eval.images:
            iio.imwrite(out_dir / f"{stem}.png", _png(rgb[i]))
            iio.imwrite(out_dir / f"{stem}_gt.png", _png(views.images[i]))
    metrics = {"split": split, "views": len(views), "resolution": [views.width, views.height],
               "background": list(cfg.data.background), "renderer": cfg.render.renderer,
               "points": model.scene.num_points, "psnr": _stats(p), "ssim": _stats(s),
               "lpips": _stats(lp) | {"backbone": "alex"} if lp is not None else lp_msg,
               "render_seconds": seconds}
    _write_json(out_dir / "metrics.json", metrics)
    _write_json(out_dir / "per_view.json", {"views": per_view})
    log.info("held-out %s (%d views, %dx%d): PSNR %.2f ± %.2f dB, SSIM %.4f ± %.4f, LPIPS %s", split, len(views),
             views.width, views.height, metrics["psnr"]["mean"], metrics["psnr"]["std"], metrics["ssim"]["mean"],
             metrics["ssim"]["std"], metrics["lpips"] if isinstance(metrics["lpips"], str)
             else f"{metrics['lpips']['mean']:.4f}")
    log.info("metrics written to %s", out_dir / "metrics.json")
    return metrics


def orbit_cameras(train: PosedViews, frames: int) -> torch.Tensor:
    """``[frames,4,4]`` cameras on a circle at the training cameras' mean distance and elevation,
    looking at the point nearest to all training optical axes, up = mean camera up."""
    V = train.viewmats.double().cpu()
    R, t = V[:, :3, :3], V[:, :3, 3]
    eyes = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    axes = R[:, 2, :]  # camera z (forward) in world coordinates
    up = -R[:, 1, :].mean(0)
    up = up / up.norm()
    # Least-squares point closest to all optical axes.
    P = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    target = torch.linalg.lstsq(P.sum(0), (P @ eyes[..., None]).sum(0)).solution[:, 0]
    rel = eyes - target
    height = float((rel @ up).mean())
    radius = float((rel - (rel @ up)[:, None] * up).norm(dim=-1).mean())
    e1 = torch.linalg.cross(up, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    if e1.norm() < 1e-6:
        e1 = torch.linalg.cross(up, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(up, e1)
    ang = torch.arange(frames, dtype=torch.float64) / frames * 2 * math.pi
    eye = target + radius * (torch.cos(ang)[:, None] * e1 + torch.sin(ang)[:, None] * e2) + height * up
    return look_at(eye, target.expand_as(eye), up).float()


def render(cfg: Config, ctx: RunContext) -> Path:
    """Write ``orbit.mp4``: the trained model along a circle of cameras around the scene."""
    model = load_model(cfg, ctx)
    train = load_views(cfg, "train", ctx.device)
    viewmats = orbit_cameras(train, cfg.eval.orbit_frames).to(ctx.device)
    Ks = train.Ks[:1].expand(viewmats.shape[0], 3, 3).contiguous()
    orbit = dataclasses.replace(train, images=train.images[:1].expand(viewmats.shape[0], -1, -1, -1),
                                masks=None, viewmats=viewmats,
                                Ks=Ks, names=[f"orbit_{i}" for i in range(viewmats.shape[0])])
    rgb, _ = render_split(model, orbit, seed=eval_seed(cfg))
    frames = _png(rgb)
    H, W = frames.shape[1:3]
    frames = np.pad(frames, ((0, 0), (0, H % 2), (0, W % 2), (0, 0)), mode="edge")  # even sizes for yuv420p
    path = ctx.run_dir / "orbit.mp4"
    imageio.mimwrite(path, list(frames), fps=cfg.eval.fps, macro_block_size=1)
    log.info("orbit video (%d frames) written to %s", len(frames), path)
    return path
