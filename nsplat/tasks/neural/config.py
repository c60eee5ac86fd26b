"""Configuration of the ``neural`` task (see :mod:`nsplat.tasks.neural`): one dataclass per section."""
from __future__ import annotations

import dataclasses
from typing import Any, Literal

from nsplat.config import ConfigError, from_dict, require_fields, to_dict
from nsplat.engine import LogConfig, op_seed
from nsplat.fitting import FitConfig, RepositionConfig
from nsplat.render import RenderConfig
from nsplat.scene import ATTRIBUTES
from nsplat.sh import MAX_VIEW_DEGREE, view_channels


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
class CaptureConfig:
    """A COLMAP capture (``data.source: colmap``; :mod:`nsplat.tasks.neural.capture`, docs/capture.md).

    Attributes:
        downscale: photos at ``1/downscale`` (read from ``<images>_<downscale>/`` when it exists).
        holdout_every: every n-th image by name is the test split (8: the Mip-NeRF 360 / 3DGS convention).
        val_every: of the other images, every n-th from the (n/2)-th is the validation split (not trained on).
        images, sparse, masks: folders relative to ``data.root``: photos, model (``null``: ``sparse/0`` or
            ``sparse``), coverage masks (``null``: none; needed only by ``geometry.init: hull``).
        normalize: move the world so the cameras' common look-at point is the origin and scale it so their
            median distance to it is ``radius`` (the units the learning rates were set in).
        near_far: render near/far planes from the SfM points' depths (without points: from the background
            sphere; :func:`nsplat.tasks.neural.capture.with_capture_render`).
        cache_dir: folder of the undistorted photos (``null``: ``<root>/nsplat_undistorted``).
    """

    downscale: int = 1
    holdout_every: int = 8
    val_every: int = 8
    images: str = "images"
    sparse: str | None = None
    masks: str | None = None
    normalize: bool = True
    radius: float = 3.2
    near_far: bool = True
    cache_dir: str | None = None

    def __post_init__(self) -> None:
        require_fields(self, downscale=">=1", radius=">0")
        for key in ("holdout_every", "val_every"):
            if getattr(self, key) < 2:
                raise ConfigError(f"data.capture.{key}: expected >= 2, got {getattr(self, key)}")


@dataclasses.dataclass
class DataConfig:
    """Where the posed images come from.

    Attributes:
        source: ``procedural`` (the embedded scene), ``nerf_synthetic`` (a folder at ``root``) or ``colmap``
            (a COLMAP capture at ``root``: ``sparse/0`` + ``images/``, settings in ``capture``).
        root: NeRF-synthetic or COLMAP scene folder (relative paths: to the repo root).
        resolution: image side after resizing (``null``: as stored).
        background: RGB composited under the RGBA images (white: NeRF's evaluation protocol).
        train_limit, val_limit, test_limit: use only the first k frames of a split (``null``: all).
    """

    source: Literal["procedural", "nerf_synthetic", "colmap"] = "procedural"
    root: str | None = None
    resolution: int | None = None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    procedural: ProceduralConfig = dataclasses.field(default_factory=ProceduralConfig)
    capture: CaptureConfig = dataclasses.field(default_factory=CaptureConfig)
    train_limit: int | None = None
    val_limit: int | None = None
    test_limit: int | None = None

    def __post_init__(self) -> None:
        if self.source in ("nerf_synthetic", "colmap") and not self.root:
            raise ConfigError(f"data.root: required when data.source is {self.source}")
        if self.source == "colmap" and self.resolution is not None:
            raise ConfigError("data.resolution: not used with data.source colmap; set data.capture.downscale")
        if self.resolution is not None and self.resolution < 8:
            raise ConfigError(f"data.resolution: expected >= 8 pixels or null, got {self.resolution}")
        if any(not 0.0 <= c <= 1.0 for c in self.background):
            raise ConfigError(f"data.background: expected RGB values in [0, 1], got {list(self.background)}")


@dataclasses.dataclass
class GeometryFitConfig(FitConfig):
    """:class:`nsplat.fitting.FitConfig` with this stage's defaults (short CPU schedule, RGB
    features rendered without shading: photographs carry their own). ``shading: sh`` makes the colour
    view-dependent (spherical harmonics up to ``geometry.sh_degree``)."""

    epochs: int = 8
    batch: int = 4
    learn: dict[str, float] = dataclasses.field(default_factory=lambda: {
        "means": 0.002, "normals": 0.01, "scales": 0.005, "opacities": 0.05, "features": 0.05})
    lr_decays: int = 2
    shading: Literal["none", "sh"] = "none"
    reposition: RepositionConfig = dataclasses.field(default_factory=lambda: RepositionConfig(every=4))


@dataclasses.dataclass
class SfmInitConfig:
    """``geometry.init: sfm`` (:func:`nsplat.tasks.neural.sfm_init.sfm_surfels`): outlier filters and the plane fit.

    Attributes:
        min_track: keep points seen in at least this many images. max_error: and with a mean
            reprojection error of at most this many pixels. k: neighbours of the normal's plane fit and of
            the isolation filter. std_ratio: isolation threshold in standard deviations.
        background_points: also make surfels of the points beyond 1.5 camera distances from the cameras'
            look-at point (the background) when a background sphere is on (``false``: the sphere alone).
        fill: add this many random points (:func:`nsplat.tasks.neural.sfm_init.fill_points`; ``0``: none) inside
            ``fill_box``: ``points`` (the box of the kept SfM surfels, grown by ``fill_margin`` times its
            size per side) or ``bbox`` (``geometry.bbox``), kept where ``fill_seen`` of the training
            views see them, with opacity ``fill_opacity`` (low, as 3DGS starts all points: a random point in
            the air must not hide the scene before the fitter has moved or faded it).
    """

    min_track: int = 3
    max_error: float = 2.0
    k: int = 8
    std_ratio: float = 2.0
    background_points: bool = True
    fill: int = 0
    fill_box: Literal["points", "bbox"] = "points"
    fill_margin: float = 0.5
    fill_seen: float = 0.8
    fill_opacity: float = 0.1

    def __post_init__(self) -> None:
        require_fields(self, min_track=">=1", max_error=">0", std_ratio=">0", fill=">=0", fill_margin=">=0",
                       fill_seen="prob")
        if not 0.0 < self.fill_opacity < 1.0:
            raise ConfigError(f"geometry.sfm.fill_opacity: expected a value in (0, 1), got {self.fill_opacity}")
        if self.k < 3:
            raise ConfigError(f"geometry.sfm.k: expected >= 3 neighbours, got {self.k}")


@dataclasses.dataclass
class BackgroundConfig:
    """What stands behind the scene in unmasked photos (:mod:`nsplat.tasks.neural.background`).

    Attributes:
        model: ``none`` (the constant ``data.background``: masked NeRF-synthetic scenes) or ``sphere``
            (surfels on a far sphere, coloured from the photos, fitted and learned with the scene).
        points: lattice points on the whole sphere (only those a training camera sees are kept).
        radius: sphere radius in median camera distances; ``null``: from the SfM points' distances.
        centre: sphere centre in the training frame (``null``: the cameras' common look-at point, the
            origin of a normalised capture).
    """

    model: Literal["none", "sphere"] = "none"
    points: int = 16384
    radius: float | None = None
    centre: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.points < 4:
            raise ConfigError(f"geometry.background.points: expected >= 4, got {self.points}")
        if self.radius is not None and self.radius <= 0:
            raise ConfigError(f"geometry.background.radius: expected > 0 or null, got {self.radius}")


@dataclasses.dataclass
class GeometryConfig:
    """Stage 1: RGB surfels fitted to the training views.

    Attributes:
        init: ``hull`` (visual hull of the training silhouettes), ``sfm`` (the SfM points of a COLMAP
            capture, filtered, with plane-fit normals: ``sfm``), ``ply`` (a PLY written by
            :meth:`nsplat.scene.SurfelScene.save_ply` with this stage's attributes, e.g. a previous
            run's ``geometry.ply``) or ``random`` (``max_points`` points uniform in ``bbox``, random
            normals, grey: a start without silhouettes or SfM points).
        ply: path of that PLY (relative: to the repo root).
        bbox: visual-hull bounds ``(xmin, ymin, zmin, xmax, ymax, zmax)``.
        grid: visual-hull voxels per side. alpha_threshold, dilate, min_seen: see
            :func:`nsplat.data.visual_hull.carve`. max_points: cap on the initial point count.
        scale_factor: initial surfel std-dev in units of the mean 3-NN spacing.
        opacity: constant opacity (nothing allocated) or ``null`` for learned per-point opacities.
        init_opacity: initial per-point opacity.
        learn: attributes fitted in this stage (rates in ``optim.learn``).
        optim: :class:`GeometryFitConfig` (``epochs: 0`` keeps the initial points).
        log: the stage's cadences in fitter steps (its progress bar follows ``log.progress``).
        prune_opacity: points whose opacity ends below this are dropped before stage 2.
        sh_degree: degree (1..3) of the view-dependent colour when ``optim.shading`` is ``sh``
            (``3·(degree+1)²`` feature channels; the first three are the mean colour, which seeds stage 2).
        sfm: :class:`SfmInitConfig`. background: :class:`BackgroundConfig` (points added to the initial ones).
    """

    init: Literal["hull", "ply", "random", "sfm"] = "hull"
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
    log: LogConfig = dataclasses.field(default_factory=lambda: LogConfig(every=10, images=0, validate=0,
                                                                        checkpoint=10))
    prune_opacity: float = 0.02
    sh_degree: int = 0
    sfm: SfmInitConfig = dataclasses.field(default_factory=SfmInitConfig)
    background: BackgroundConfig = dataclasses.field(default_factory=BackgroundConfig)

    def channels(self) -> int:
        """Feature channels of the stage-1 scene: RGB, or RGB spherical harmonics up to ``sh_degree``."""
        return view_channels(self.sh_degree) if self.optim.shading == "sh" else 3

    def __post_init__(self) -> None:
        if not 0 <= self.sh_degree <= MAX_VIEW_DEGREE:
            raise ConfigError(f"geometry.sh_degree: expected 0..{MAX_VIEW_DEGREE}, got {self.sh_degree}")
        if (self.sh_degree > 0) != (self.optim.shading == "sh"):
            raise ConfigError(f"geometry.sh_degree: expected >= 1 exactly when geometry.optim.shading is sh, got "
                              f"{self.sh_degree} with shading {self.optim.shading!r}")
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
        start: fraction of stage 2 after which the discriminator and the adversarial term join (the
            image loss alone before; first GAN step ``round(start · neural.steps)``); the discriminator's
            rate decays to ``neural.lr_final`` over its own steps.
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
    start: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.start < 1.0:
            raise ConfigError(f"neural.gan.start: expected a fraction of the steps in [0, 1), got {self.start}")


@dataclasses.dataclass
class NeuralConfig:
    """Stage 2: learned point features + U-Net shader (+ PatchGAN).

    Attributes:
        steps: optimisation steps; 0: no stage 2 (the stage-1 surfels are the model, evaluated as
            ``eval_geometry.json`` and returned as the run's metrics: the point-only baseline). batch: training views per step (the global batch: under torchrun
            each of the P processes renders ``batch / P`` of them, docs/distributed.md).
        chunk: views rendered (and back-propagated) at once by one process; a step's share is rendered
            in chunks of this many views with gradients accumulated (``null``: the whole share at once).
            Same gradients within float rounding; with the GAN on and more than one chunk the generator's
            forward runs twice (once for the discriminator's step, once for its own).
        features: feature channels C per point.
        feature_init_std: std-dev of the random initial features beyond the first three (colour).
        alpha_input: feed the splatted coverage to the U-Net as an extra channel.
        residual: the U-Net predicts a residual (in logit space, zero-initialised head) around the
            first three splatted feature channels, which start as the stage-1 colours composited on
            the data background; so stage 2 starts from the stage-1 render.
        view_colour: keep stage 1's view-dependent colour (needs ``geometry.optim.shading: sh``): the
            stage-2 points also carry stage 1's higher SH coefficients (``3·((L+1)² − 1)`` more feature
            channels, learned with ``learn.features``), and the first three splatted channels are the
            SH colour seen from each camera (:func:`nsplat.sh.view_colour`) instead of the mean colour; so
            stage 2 starts from the stage-1 render itself. ``false``: the mean colour (nothing allocated).
        learn: learnable point attributes → learning rate (others are frozen buffers).
        lr: U-Net learning rate. betas: its Adam decay rates.
        lr_final: every learning rate decays exponentially to this fraction at the last step.
        ssim_weight: share of D-SSIM in the image loss, ``(1 − s)·L1 + s·D-SSIM`` (0: L1 only).
        unet, gan: the networks.
    """

    steps: int = 400
    batch: int = 4
    chunk: int | None = None
    features: int = 16
    feature_init_std: float = 0.1
    alpha_input: bool = True
    residual: bool = True
    view_colour: bool = False
    learn: dict[str, float] = dataclasses.field(default_factory=lambda: {"features": 0.01, "means": 1e-4,
                                                                         "opacities": 0.01})
    lr: float = 1e-3
    betas: tuple[float, float] = (0.5, 0.999)
    lr_final: float = 0.1
    ssim_weight: float = 0.0
    unet: UNetConfig = dataclasses.field(default_factory=UNetConfig)
    gan: GanConfig = dataclasses.field(default_factory=GanConfig)

    def gan_start_step(self) -> int:
        """First stage-2 step with the discriminator: ``round(gan.start · steps)`` (< ``steps``)."""
        return min(round(self.gan.start * self.steps), self.steps - 1)

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise ConfigError(f"neural.steps: expected >= 0, got {self.steps}")
        for key in ("batch", "features"):
            if getattr(self, key) < 1:
                raise ConfigError(f"neural.{key}: expected >= 1, got {getattr(self, key)}")
        if self.chunk is not None and self.chunk < 1:
            raise ConfigError(f"neural.chunk: expected >= 1 or null, got {self.chunk}")
        if self.chunk is not None and self.chunk < self.batch and "batch" in (self.unet.norm, self.gan.norm):
            raise ConfigError("neural.chunk: batch norm statistics would depend on the chunks; use norm group, "
                              "instance or none with chunks smaller than neural.batch")
        if self.residual and self.features < 3:
            raise ConfigError(f"neural.residual: needs neural.features >= 3, got {self.features}")
        bad = [a for a in self.learn if a not in ATTRIBUTES]
        if bad:
            raise ConfigError(f"neural.learn: unknown attribute(s) {bad}; expected a subset of {list(ATTRIBUTES)}")
        if not 0.0 <= self.ssim_weight <= 1.0:
            raise ConfigError(f"neural.ssim_weight: expected a value in [0, 1], got {self.ssim_weight}")
        if not 0.0 < self.lr_final <= 1.0:
            raise ConfigError(f"neural.lr_final: expected a fraction in (0, 1], got {self.lr_final}")


@dataclasses.dataclass
class EvalConfig:
    """Evaluation and rendering.

    Attributes:
        split: held-out split evaluated at the end of training (and by ``eval`` by default).
        images: write rendered/GT PNGs. orbit_frames, fps: the ``render`` command's orbit video.
        val_views: views per split in the training-time validation (``log.validate``; ``history.json``).
        render: overrides of the top-level ``render`` section for every evaluation render (held-out
            metrics, training-time validation, the orbit video), e.g. ``eval.render: {samples: 80}``;
            empty (default): evaluate with the training settings. See :meth:`Config.eval_render`.
        geometry: also evaluate stage 1 alone (``geometry.ply`` rendered as RGB surfels) on val and
            ``split`` after training (``eval_geometry.json``).
        draws: independent op draws per evaluation render (held-out metrics, training-time validation,
            the orbit video) whose feature images are averaged before the U-Net: a lower-variance estimate
            of the expected feature image the shader was trained on (unlike more ``samples``, which shifts
            it); costs ``draws`` splats per view. 1 (default): one draw.
    """

    split: Literal["train", "val", "test"] = "test"
    val_views: int = 8
    images: bool = True
    orbit_frames: int = 60
    fps: int = 20
    render: dict[str, Any] = dataclasses.field(default_factory=dict)
    geometry: bool = True
    draws: int = 1

    def __post_init__(self) -> None:
        if self.draws < 1:
            raise ConfigError(f"eval.draws: expected >= 1, got {self.draws}")


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
        self.eval_render()  # unknown or invalid eval.render keys fail at load
        if "opacities" in self.neural.learn and self.geometry.opacity is not None:
            raise ConfigError("neural.learn: 'opacities' needs geometry.opacity: null (per-point opacities)")
        if self.neural.view_colour and self.geometry.optim.shading != "sh":
            raise ConfigError("neural.view_colour: needs geometry.optim.shading: sh (a view-dependent stage-1 "
                              f"colour), got {self.geometry.optim.shading!r}")
        if self.data.source != "colmap" and self.geometry.init == "sfm":
            raise ConfigError("geometry.init: sfm needs data.source colmap (SfM points)")
        if self.data.source != "colmap" and self.geometry.background.model != "none":
            raise ConfigError("geometry.background.model: sphere needs data.source colmap (unmasked photos)")

    def view_rest(self) -> int:
        """Feature channels of the higher SH coefficients the stage-2 points carry (``neural.view_colour``)."""
        return self.geometry.channels() - 3 if self.neural.view_colour else 0

    def eval_seed(self) -> int:
        """Op seed of every evaluation render (validation, test, orbit, the viewer): fixed by ``seed``."""
        return op_seed(self.seed, "eval")

    def eval_render(self) -> RenderConfig:
        """The render settings of evaluation: ``render`` with the ``eval.render`` overrides applied."""
        if not self.eval.render:
            return self.render
        return from_dict(RenderConfig, {**to_dict(self.render), **self.eval.render}, prefix="eval.render.")
