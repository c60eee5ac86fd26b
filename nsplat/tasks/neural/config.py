"""Configuration of the ``neural`` task (see :mod:`nsplat.tasks.neural`): one dataclass per section."""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal

from nsplat.config import ConfigError, from_dict, require, require_fields, to_dict
from nsplat.fitting import FitConfig
from nsplat.models import PatchGANConfig, UNetConfig
from nsplat.render.renderer import RenderConfig
from nsplat.render.sh import MAX_VIEW_DEGREE, view_channels
from nsplat.run.engine import LogConfig, op_seed
from nsplat.scene import ATTRIBUTES
from nsplat.tasks.neural.data_config import DataConfig
from nsplat.tasks.neural.precision import Precision

#: The scene's box without silhouettes and without ``geometry.bbox``: the training frame's cube.
FRAME_BOX = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)


@dataclasses.dataclass
class GeometryFitConfig(FitConfig):
    """Stage 1's fitter settings: :class:`nsplat.fitting.FitConfig` (whose docstring documents every field),
    with this stage's defaults for the fields below.

    Attributes:
        epochs: 8 (a short CPU schedule). batch: 4. learn: smaller position and size rates than the paper's.
        lr_decays: 2.
        shading: ``none`` (RGB features rendered as they are: photographs carry their own shading) or ``sh``
            (view-dependent colour, spherical harmonics up to ``geometry.sh_degree``).
    """

    epochs: int = 8
    batch: int = 4
    learn: dict[str, float] = dataclasses.field(default_factory=lambda: {
        "means": 0.002, "normals": 0.01, "scales": 0.005, "opacities": 0.05, "features": 0.05})
    lr_decays: int = 2
    shading: Literal["none", "sh"] = "none"


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
        require_fields(self, fill_opacity="open", k=">=3")


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
        require_fields(self, points=">=4", radius=">0", centre="finite")


@dataclasses.dataclass
class GeometryConfig:
    """Stage 1: RGB surfels fitted to the training views.

    Attributes:
        init: ``hull`` (visual hull of the training silhouettes), ``sfm`` (the SfM points of a COLMAP
            capture, filtered, with plane-fit normals: ``sfm``), ``ply`` (a previous run's ``geometry.ply``
            with this stage's attributes, a 3D Gaussian splatting PLY such as ``export --format 3dgs``
            writes, or any point cloud with ``x y z`` and optional normals and colours:
            :func:`nsplat.tasks.neural.starts._ply_scene`) or ``random`` (``max_points`` points uniform
            in ``bbox``, random normals, grey: a start without silhouettes or SfM points) or ``view_fill``
            (``max_points`` random points in ``bbox`` that ``sfm.fill_seen`` of the training cameras see: their
            common view; opacity ``sfm.fill_opacity``, colours from the photos) or ``auto``: ``sfm`` for a COLMAP
            capture; for a ``transforms`` capture the point cloud its ``ply_file_path`` names (moved with the
            cameras), else the hull when ``data.capture.masks`` is set, else a COLMAP model's points beside the
            file or points triangulated from the photos (:mod:`nsplat.data.triangulate`), else ``view_fill``;
            ``hull`` otherwise.
        ply: path of that PLY (relative: to the repo root).
        bbox: the scene's box ``(xmin, ymin, zmin, xmax, ymax, zmax)`` (hull, random starts); ``null``: from the data
            (the hull's: :func:`~nsplat.data.visual_hull.silhouette_box`; else :data:`FRAME_BOX`).
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
        stall_epochs: stop with an error when, at the first validation after this many epochs and 100 steps,
            the val PSNR is under 1 dB above both the start's and a flat image's (0: no check; docs/capture.md).
    """

    init: Literal["hull", "ply", "random", "sfm", "view_fill", "auto"] = "hull"
    ply: str | None = None
    bbox: tuple[float, float, float, float, float, float] | None = None
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
    log: LogConfig = dataclasses.field(default_factory=LogConfig)
    prune_opacity: float = 0.02
    sh_degree: int = 0
    sfm: SfmInitConfig = dataclasses.field(default_factory=SfmInitConfig)
    background: BackgroundConfig = dataclasses.field(default_factory=BackgroundConfig)
    stall_epochs: float = 3.0

    def channels(self) -> int:
        """Feature channels of the stage-1 scene: RGB, or RGB spherical harmonics up to ``sh_degree``."""
        return view_channels(self.sh_degree) if self.optim.shading == "sh" else 3

    def __post_init__(self) -> None:
        require(0 <= self.sh_degree <= MAX_VIEW_DEGREE, "sh_degree", f"0..{MAX_VIEW_DEGREE}", self.sh_degree)
        require((self.sh_degree > 0) == (self.optim.shading == "sh"), "sh_degree",
                f">= 1 exactly when optim.shading is sh (it is {self.optim.shading!r})", self.sh_degree)
        require(self.init != "ply" or bool(self.ply), "ply", "a PLY file with init: ply", self.ply)
        box = self.bbox or (0, 0, 0, 1, 1, 1)
        require(all(math.isfinite(v) for v in box) and all(a < b for a, b in zip(box[:3], box[3:])), "bbox",
                "null (from the data) or finite (xmin, ymin, zmin, xmax, ymax, zmax) with min < max", self.bbox)
        require_fields(self, grid=">=8", alpha_threshold="unit", dilate=">=0", min_seen="unit", max_points=">=1",
                       scale_factor=">0", opacity="prob", init_opacity="open", prune_opacity="unit",
                       stall_epochs=">=0")
        require(all(a in ATTRIBUTES for a in self.learn), "learn", f"a subset of {list(ATTRIBUTES)}", self.learn)
        require(self.opacity is None or "opacities" not in self.learn, "learn",
                "no 'opacities' with a constant opacity (set opacity: null for per-point opacities)", self.learn)


@dataclasses.dataclass
class GanConfig(PatchGANConfig):
    """Conditional PatchGAN (:class:`nsplat.models.PatchDiscriminator`; its shape, ``width``, ``layers`` and
    ``norm``, is :class:`nsplat.models.PatchGANConfig`) and the adversarial loss.

    Attributes:
        enabled: train with the adversarial term (``false``: L1 only; no discriminator is built).
        mode: ``lsgan`` or ``bce``. weight: adversarial weight (pix2pix: 1). lambda_l1: weight of the image
            loss (L1 + D-SSIM) beside it (pix2pix: 100).
        lr, betas: discriminator Adam.
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
    start: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require_fields(self, weight=">=0", lambda_l1=">=0", lr=">0", betas="rate")
        require(0.0 <= self.start < 1.0, "start", "a fraction of the steps in [0, 1)", self.start)


@dataclasses.dataclass
class NeuralConfig:
    """Stage 2: learned point features + U-Net shader (+ PatchGAN).

    Attributes:
        steps: optimisation steps; 0: no stage 2 (the stage-1 surfels are the model, evaluated as
            ``eval_geometry.json`` and returned as the run's metrics: the point-only baseline). batch: training views
            per step (the global batch: under torchrun
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
            SH colour seen from each camera (:func:`nsplat.render.sh.view_colour`) instead of the mean colour; so
            stage 2 starts from the stage-1 render itself. ``false``: the mean colour (nothing allocated).
        learn: learnable point attributes → learning rate (others are frozen buffers).
        lr: U-Net learning rate. betas: its Adam decay rates.
        lr_final: every learning rate decays exponentially to this fraction at the last step.
        ssim_weight: share of D-SSIM in the image loss, ``(1 − s)·L1 + s·D-SSIM`` (0: L1 only).
        precision: compute precision of the U-Net and the discriminator in training and evaluation:
            ``float32``, ``bfloat16`` (autocast; the op, losses, weights, optimiser state and checkpoints stay
            float32) or ``auto`` (bfloat16 where the CPU multiplies it natively, AMX-BF16 or AVX512-BF16,
            else float32; float32 on CUDA; chosen at start-up and logged: :mod:`nsplat.tasks.neural.precision`).
        unet, gan: the networks.
        select: the model is stage 2's ``last`` state or ``best_val``: the state at the validation of highest val
            PSNR (stage 2's length chosen on the validation views; kept in the checkpoint for eval and resume).
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
    precision: Precision = "auto"
    select: Literal["last", "best_val"] = "last"
    unet: UNetConfig = dataclasses.field(default_factory=UNetConfig)
    gan: GanConfig = dataclasses.field(default_factory=GanConfig)

    def gan_start_step(self) -> int:
        """First stage-2 step with the discriminator: ``round(gan.start · steps)`` (< ``steps``)."""
        return min(round(self.gan.start * self.steps), self.steps - 1)

    def __post_init__(self) -> None:
        require_fields(self, steps=">=0", batch=">=1", chunk=">=1", features=">=1", feature_init_std=">=0", lr=">0",
                       betas="rate", lr_final="prob", ssim_weight="unit")
        require(self.chunk is None or self.chunk >= self.batch or "batch" not in (self.unet.norm, self.gan.norm),
                "chunk", "a whole batch with batch norm (its statistics would depend on the chunks; use norm group, "
                "instance or none)", self.chunk)
        require(not self.residual or self.features >= 3, "features", ">= 3 with residual: true", self.features)
        require(all(a in ATTRIBUTES and v > 0 for a, v in self.learn.items()), "learn",
                f"positive rates for attributes among {list(ATTRIBUTES)}", self.learn)


@dataclasses.dataclass
class EvalConfig:
    """Evaluation and rendering.

    Attributes:
        split: held-out split evaluated at the end of training (and by ``eval`` by default).
        protocol: how held-out views are scored (:mod:`nsplat.evaluation.protocol`): ``standard`` (the published
            tables: render and ground truth quantised to 8 bits, PSNR, SSIM over zero-padded images as in 3D
            Gaussian splatting, LPIPS VGG and AlexNet when installed) or ``nsplat`` (float images, SSIM over
            the valid region). Training-time validation (``history.json``) stays on float images.
        images: write rendered/GT PNGs. sheet_views: views on the comparison sheet ``sheet.png`` (ground
            truth | render | error heat map; evenly spread; 0: no sheet).
        orbit_frames, fps: the ``render`` command's frames (orbit and smooth paths) and frame rate.
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
    protocol: Literal["standard", "nsplat"] = "standard"
    val_views: int = 8
    images: bool = True
    sheet_views: int = 8
    orbit_frames: int = 60
    fps: int = 20
    render: dict[str, Any] = dataclasses.field(default_factory=dict)
    geometry: bool = True
    draws: int = 1

    def __post_init__(self) -> None:
        require_fields(self, val_views=">=1", sheet_views=">=0", orbit_frames=">=1", fps=">=1", draws=">=1")


@dataclasses.dataclass
class Config:
    """Task ``neural`` (see :mod:`nsplat.tasks.neural`).

    Attributes:
        task: ``neural``. seed: the run seed (data order, initial features, every op seed).
        data: :class:`DataConfig`, the posed images. render: the render settings of training
            (:class:`nsplat.render.renderer.RenderConfig`). geometry: :class:`GeometryConfig`, stage 1.
        neural: :class:`NeuralConfig`, stage 2. log: the stage-2 cadences (:class:`nsplat.run.engine.LogConfig`).
        eval: :class:`EvalConfig`, evaluation.
    """

    task: str = "neural"
    seed: int = 0
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    neural: NeuralConfig = dataclasses.field(default_factory=NeuralConfig)
    log: LogConfig = dataclasses.field(default_factory=LogConfig)
    eval: EvalConfig = dataclasses.field(default_factory=EvalConfig)

    def __post_init__(self) -> None:
        require(self.task == "neural", "task", "'neural'", self.task)
        require_fields(self, seed=">=0")
        self.eval_render()  # unknown or invalid eval.render keys fail at load
        if "opacities" in self.neural.learn and self.geometry.opacity is not None:
            raise ConfigError("neural.learn: 'opacities' needs geometry.opacity: null (per-point opacities)")
        if self.neural.view_colour and self.geometry.optim.shading != "sh":
            raise ConfigError("neural.view_colour: needs geometry.optim.shading: sh (a view-dependent stage-1 "
                              f"colour), got {self.geometry.optim.shading!r}")
        if self.data.source != "colmap" and self.geometry.init == "sfm":
            raise ConfigError("geometry.init: sfm needs data.source colmap (SfM points)")
        if not self.data.is_capture() and self.geometry.background.model != "none":
            raise ConfigError("geometry.background.model: sphere needs data.source colmap or transforms (unmasked "
                              "photos)")

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
