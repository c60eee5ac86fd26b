"""Configuration of the ``refine`` task (see :mod:`nsplat.tasks.refine`)."""
from __future__ import annotations

import dataclasses
import math
from typing import Literal

from nsplat.config import ConfigError, require, require_fields
from nsplat.data.fusion import FusionConfig
from nsplat.data.tracking import TrackingConfig
from nsplat.render.renderer import RenderConfig
from nsplat.run.engine import LogConfig
from nsplat.scene import SceneConfig
from nsplat.tasks.refine.filtering import FilterConfig
from nsplat.tasks.refine.room import RoomSpec


@dataclasses.dataclass
class NerfSource:
    """NeRF-synthetic frames with perturbed poses and a PLY initial cloud.

    Attributes:
        root: scene folder; empty: ``<data root>/nerf_synthetic/lego_400`` (:mod:`nsplat.data.paths`).
        split: frames to refine against.
        resolution: image width = height in pixels.
        limit: use the first ``limit`` frames (0: all).
        cloud: PLY written by ``SurfelScene.save_ply`` with the attributes ``scene`` allocates.
        rot_deg, trans_frac: pose perturbation (degrees; fraction of the cloud's largest extent).
        perturb_seed: seed of the perturbation.
    """

    root: str = ""
    split: str = "train"
    resolution: int = 100
    limit: int = 0
    cloud: str = ""
    rot_deg: float = 2.0
    trans_frac: float = 0.02
    perturb_seed: int = 0

    def __post_init__(self) -> None:
        require_fields(self, resolution=">=8", limit=">=0", rot_deg=">=0", trans_frac=">=0", perturb_seed=">=0")


@dataclasses.dataclass
class RGBDSource:
    """A real RGB-D sequence with a SLAM / odometry trajectory (:mod:`nsplat.data.rgbd`), fused into the initial
    cloud (:mod:`nsplat.data.fusion`) or with the SLAM system's own cloud (``cloud``).

    Attributes:
        root: the sequence folder; empty: ``<data root>/rgbd/tum_fr1_rpy_50`` (:mod:`nsplat.data.paths`).
        layout: ``tum`` (rgb.txt, depth.txt, TUM trajectory files) or ``folder`` (``<frame>.color.png``,
            ``<frame>.depth.png``, ``<frame>.pose.txt`` camera → world 4×4, and ``intrinsics_file``).
        trajectory: the trajectory to refine (TUM layout; relative to ``root`` unless absolute); ``estimate``:
            track the frames (:mod:`nsplat.data.tracking`; every frame, as a SLAM system would);
            ``auto``: ``odometry.txt`` when the folder has one, else ``estimate``.
        groundtruth: a ground-truth trajectory for ATE / RPE ("" : none). A trajectory equal to it (every pose
            within 1e-6, up to the world frame) is warned about: its ATE measures nothing.
        trajectory_alignment: how ATE aligns the trajectory to the ground truth: ``se3`` (rigid, RGB-D) or
            ``sim3`` (with a scale, e.g. a monocular trajectory); RPE needs none.
        intrinsics_file: the folder layout's 3×3 intrinsics file ("" : ``intrinsics``; the folder layout has no
            preset, one of the two is required).
        camera: a TUM camera preset (``fr1``, ``fr2``, ``fr3``) used by the TUM layout when ``intrinsics`` is empty.
        intrinsics: ``[fx, fy, cx, cy]`` in OpenCV's pixel convention (overrides the preset).
        distortion: OpenCV ``[k1, k2, p1, p2, k3]`` with ``intrinsics`` (empty: none).
        depth_intrinsics: the depth camera's own ``[fx, fy, cx, cy]`` (OpenCV convention, no distortion) when its
            images are not registered to the colour camera (7-Scenes); empty: the depth is registered.
        depth_to_color: with ``depth_intrinsics``, the depth camera → colour camera rigid transform (4×4 row-major
            or its first 12 numbers, metres; empty: identity). The depth is reprojected into the colour camera
            (the nearest reading wins a pixel) before undistortion and downscaling.
        depth_scale: depth PNG units per metre (5000 TUM, 1000 millimetres). A scale that makes the depth
            disagree with the given trajectory's motion is an error (:mod:`nsplat.data.depth_checks`).
        depth_range: ``[min, max]`` valid depth in metres (the raw value 65535, a saturated or invalid reading,
            is invalid whatever the range).
        max_dt: largest time difference (s) when pairing RGB, depth and poses.
        downscale: integer image downscale (2: 640×480 → 320×240).
        stride: use every ``stride``-th frame. limit: at most this many frames (0: all).
        holdout_every: every this many frames (from the first) is held out of the refinement and scored.
        valid: pixels scored and fitted: ``depth`` (inside the undistorted photo and with a depth reading, as the
            paper masks RGB pixels without depth) or ``image`` (inside the undistorted photo).
        cloud: a PLY of the SLAM system's surfels (``x y z``; ``nx ny nz``, ``red green blue`` and ``radius``
            when present) instead of fusing the depth.
        fusion: :class:`nsplat.data.fusion.FusionConfig`.
        tracking: :class:`nsplat.data.tracking.TrackingConfig` (with ``trajectory: estimate`` or ``retrack``).
        retrack: with a given trajectory, re-track the frames before refining (each frame predicted by the
            trajectory's own relative motion, registered to the model of the frames before it, then
            ``tracking.rounds`` re-alignments): a wide basin for a trajectory far off. "Before" still scores the
            trajectory as given.
    """

    root: str = ""
    layout: Literal["tum", "folder"] = "tum"
    trajectory: str = "auto"
    groundtruth: str = "groundtruth.txt"
    trajectory_alignment: Literal["se3", "sim3"] = "se3"
    intrinsics_file: str = ""
    camera: str = "fr1"
    intrinsics: list[float] = dataclasses.field(default_factory=list)
    distortion: list[float] = dataclasses.field(default_factory=list)
    depth_intrinsics: list[float] = dataclasses.field(default_factory=list)
    depth_to_color: list[float] = dataclasses.field(default_factory=list)
    depth_scale: float = 5000.0
    depth_range: list[float] = dataclasses.field(default_factory=lambda: [0.1, 5.0])
    max_dt: float = 0.02
    downscale: int = 2
    stride: int = 1
    limit: int = 0
    holdout_every: int = 8
    valid: Literal["depth", "image"] = "depth"
    cloud: str = ""
    fusion: FusionConfig = dataclasses.field(default_factory=FusionConfig)
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)
    retrack: bool = False

    def __post_init__(self) -> None:
        require_fields(self, depth_scale=">0", max_dt=">0", downscale=">=1", stride=">=1", limit=">=0",
                       holdout_every=">=0")
        require(len(self.depth_range) == 2 and 0 <= self.depth_range[0] < self.depth_range[1], "depth_range",
                "[min, max] metres with 0 <= min < max", self.depth_range)
        require(not self.intrinsics or (len(self.intrinsics) == 4 and all(math.isfinite(v) for v in self.intrinsics)
                                        and min(self.intrinsics[:2]) > 0), "intrinsics",
                "[] (a camera preset) or [fx, fy, cx, cy] with fx, fy > 0", self.intrinsics)
        require(not self.distortion or (len(self.distortion) == 5 and all(math.isfinite(v) for v in self.distortion)),
                "distortion", "[] or [k1, k2, p1, p2, k3]", self.distortion)
        require(self.holdout_every != 1, "holdout_every", "0 (none) or >= 2 (1 would hold out every frame)",
                self.holdout_every)
        require(self.layout != "folder" or bool(self.intrinsics_file or self.intrinsics), "intrinsics_file",
                "the folder layout's intrinsics: a 3×3 matrix file (data.rgbd.intrinsics_file, e.g. "
                "camera-intrinsics.txt) or data.rgbd.intrinsics [fx, fy, cx, cy] (the camera presets are TUM's)",
                self.intrinsics_file)
        require(not self.depth_intrinsics or (len(self.depth_intrinsics) == 4 and all(
            math.isfinite(v) for v in self.depth_intrinsics) and min(self.depth_intrinsics[:2]) > 0),
                "depth_intrinsics", "[] (registered depth) or [fx, fy, cx, cy] with fx, fy > 0",
                self.depth_intrinsics)
        require(not self.depth_to_color or (self.depth_intrinsics and len(self.depth_to_color) in (12, 16)
                                            and all(math.isfinite(v) for v in self.depth_to_color)),
                "depth_to_color", "[] or 12 / 16 numbers (a 4×4 row-major rigid transform) with depth_intrinsics",
                self.depth_to_color)


@dataclasses.dataclass
class DataConfig:
    """Where frames, cameras and the initial cloud come from.

    Attributes:
        source: ``room`` (synthetic benchmark), ``nerf`` (NeRF-synthetic + PLY cloud) or ``rgbd`` (a real RGB-D
            sequence with its trajectory).
        room: the room benchmark's settings.
        nerf: the NeRF-synthetic settings.
        rgbd: the RGB-D sequence's settings.
        cache_dir: cache folder (relative to the repository root unless absolute).
        init_opacity: initial opacity of the cloud's points (where opacity is per point).
    """

    source: Literal["room", "nerf", "rgbd"] = "room"
    room: RoomSpec = dataclasses.field(default_factory=RoomSpec)
    nerf: NerfSource = dataclasses.field(default_factory=NerfSource)
    rgbd: RGBDSource = dataclasses.field(default_factory=RGBDSource)
    cache_dir: str = "data_cache"
    init_opacity: float = 0.9

    def __post_init__(self) -> None:
        require_fields(self, init_opacity="open")


@dataclasses.dataclass
class ShadingConfig:
    """How albedo becomes colour.

    Attributes:
        model: ``albedo`` (none), ``sh`` (2nd-order SH irradiance) or ``lambert`` (the paper's camera-fixed
            lights, :mod:`nsplat.render.shading`).
        learn_sh: make the 9×C SH coefficients learnable. ambient: their initial uniform radiance (>= 0).
    """

    model: Literal["albedo", "sh", "lambert"] = "sh"
    learn_sh: bool = True
    ambient: float = 1.0

    def __post_init__(self) -> None:
        require_fields(self, ambient=">=0")


@dataclasses.dataclass
class PoseConfig:
    """Camera corrections (see :class:`nsplat.tasks.refine.poses.CameraCorrection`).

    Attributes:
        learn: learn a per-camera SE(3) correction. learn_focal: learn a focal-length correction.
        shared_focal: one focal correction for all cameras (one lens).
        frozen: indices of cameras kept fixed (e.g. an anchor fixing the gauge).
        pivot: rotation pivot of the corrections: ``scene`` (the initial cloud's median depth on each camera's
            optical axis; decouples rotation from translation, see :mod:`nsplat.tasks.refine.poses`) or
            ``centre`` (the optical centre).
        odometry_weight: weight of the odometry prior of a sequence (0: none): the mean over consecutive training
            frames of ``(‖Δt‖/σ_t)² + (‖ΔR‖_F/√2/σ_r)²``, ``Δ`` the difference of their corrections
            (:func:`nsplat.tasks.refine.poses.odometry_prior`): the trajectory's frame-to-frame motion is trusted to
            ``odometry_sigma`` and its drift is what the images correct (an odometry edge of a pose graph).
        odometry_sigma: ``[σ_t metres, σ_r radians]`` of that prior.
        motion_weight: weight of the smooth-motion prior of a sequence with timestamps (0: none): the mean squared
            acceleration of the optical centres over ``motion_sigma²`` (m/s², :func:`nsplat.tasks.refine.poses.
            motion_prior`), over the training cameras in time order, and over the whole trajectory when the held-out
            cameras are fitted.
        motion_sigma: the acceleration (m/s²) the prior expects of the camera.
    """

    learn: bool = True
    learn_focal: bool = False
    shared_focal: bool = True
    frozen: list[int] = dataclasses.field(default_factory=list)
    pivot: Literal["scene", "centre"] = "centre"
    odometry_weight: float = 0.0
    odometry_sigma: list[float] = dataclasses.field(default_factory=lambda: [0.005, 0.01])
    motion_weight: float = 0.0
    motion_sigma: float = 0.5

    def __post_init__(self) -> None:
        require_fields(self, frozen=">=0", odometry_weight=">=0", motion_weight=">=0", motion_sigma=">0")
        require(len(self.odometry_sigma) == 2 and min(self.odometry_sigma) > 0, "odometry_sigma",
                "[σ_t, σ_r] > 0", self.odometry_sigma)


@dataclasses.dataclass
class ExposureConfig:
    """A per-frame affine exposure ``gain · image + bias`` (per channel) after rendering, for cameras with
    auto-exposure (the TUM Kinects). The first training frame keeps gain 1 and bias 0 (it fixes the scale that
    albedo and shading share with the gains).

    Attributes:
        learn: allocate and learn the log-gains and biases (nothing allocated otherwise); their Adam rate is
            ``optim.learn.exposure``.
    """

    learn: bool = False


@dataclasses.dataclass
class HeldoutConfig:
    """Held-out frames (``data.rgbd.holdout_every``): after the refinement their cameras (and exposures) are fitted
    to the frozen scene, as pose-refining methods do before scoring a held-out view.

    Attributes:
        steps: Adam steps of the fit (0: score at the trajectory's poses).
        fit_before: fit them the same way to the initial scene for the "before" figures (the fair protocol:
            both sides scored after the same fit; the figures at the trajectory's poses are kept as
            ``heldout_unfitted``); false: "before" scores them at the trajectory's poses.
        lr_pose: rate of the pose twists. lr_exposure: rate of the exposures (when learned).
        decay_every: halve the rates every this many steps (0: constant).
    """

    steps: int = 100
    fit_before: bool = True
    lr_pose: float = 0.002
    lr_exposure: float = 0.005
    decay_every: int = 40

    def __post_init__(self) -> None:
        require_fields(self, steps=">=0", lr_pose=">0", lr_exposure=">0", decay_every=">=0")


@dataclasses.dataclass
class OptimConfig:
    """Optimisation schedule.

    Attributes:
        steps: optimisation steps.
        batch: views per step.
        schedule: ``joint`` (poses and scene every step) or ``alternating`` (``alternate_every``
            steps of poses, then as many of scene + shading, and so on, starting with poses).
        alternate_every: phase length of the alternating schedule.
        warmup: the first ``warmup`` steps update only the parameter groups in ``warmup_groups``
            (before the schedule above starts), e.g. registering the cameras to the fixed initial
            cloud before the geometry may move. On the room benchmark this converged more slowly
            than joint optimisation (docs/results.md), so the room config uses 0.
        warmup_groups: group names updated during the warm-up: ``pose``, ``focal``, ``means``,
            ``normals``, ``scales``, ``opacities``, ``features``, ``sh``.
        decay_every: halve every learning rate every this many steps (0: constant), counted from
            the end of the warm-up.
        decay: the factor applied at each decay.
        learn: Adam learning rate per group: scene attributes (raw storage units of
            :class:`SurfelScene`; used for the attributes ``scene.learn`` makes learnable), ``sh``, ``pose``
            (twist: metres / radians), ``focal`` (log focal) and ``exposure`` (log-gain and bias).
    """

    steps: int = 300
    batch: int = 4
    schedule: Literal["joint", "alternating"] = "joint"
    alternate_every: int = 10
    warmup: int = 0
    warmup_groups: list[str] = dataclasses.field(default_factory=lambda: ["pose", "focal", "features", "sh"])
    decay_every: int = 0
    decay: float = 0.5
    learn: dict[str, float] = dataclasses.field(default_factory=lambda: {
        "means": 1e-3, "normals": 1e-2, "scales": 1e-2, "opacities": 5e-2, "features": 1e-2, "sh": 1e-2,
        "pose": 1e-3, "focal": 1e-4, "exposure": 5e-3})

    def __post_init__(self) -> None:
        self.learn = {**OptimConfig.__dataclass_fields__["learn"].default_factory(), **self.learn}
        require(all(g in GROUPS and v > 0 for g, v in self.learn.items()), "learn",
                f"positive rates for groups among {list(GROUPS)}", self.learn)
        require(all(g in GROUPS for g in self.warmup_groups), "warmup_groups", f"names from {list(GROUPS)}",
                self.warmup_groups)
        require_fields(self, steps=">=0", batch=">=1", alternate_every=">=1", warmup=">=0", decay_every=">=0",
                       decay="prob")


#: Optimiser parameter-group names: camera groups (pose, focal, exposure), then scene + shading groups.
CAMERA_GROUPS = ("pose", "focal", "exposure")
GROUPS = CAMERA_GROUPS + ("means", "normals", "scales", "opacities", "features", "sh")


@dataclasses.dataclass
class Config:
    """Configuration of the ``refine`` task.

    Attributes:
        task: ``refine``. seed: the run seed (batch order, every op seed).
        data: :class:`DataConfig`, frames, cameras and the initial cloud. scene: which point attributes exist
            and are learned (:class:`nsplat.scene.SceneConfig`). shading: :class:`ShadingConfig`.
        poses: :class:`PoseConfig`. exposure: :class:`ExposureConfig`. heldout: :class:`HeldoutConfig`.
        render: the render settings (:class:`nsplat.render.renderer.RenderConfig`).
        optim: :class:`OptimConfig`. mask_loss: restrict the loss to the frames' valid pixels.
        depth_loss: weight of the relative depth error of RGB-D frames (:func:`nsplat.tasks.refine.optimisers.depth_l1`:
            the rendered depth against the sensor's, on the loss pixels with a reading) added to the L1 image loss
            (0: images only, the paper's loss).
        coverage_mask: also leave out of the loss the pixels where the current render's (detached) alpha is
            below this, in [0, 1] (0: off). Reference pixels that no point covers (parts of the room no keyframe
            saw) cannot be explained by any pose; against the background colour they pull every camera towards
            showing more of the cloud, a bias of the pose estimate.
        filter: the outlier filter (:class:`nsplat.tasks.refine.filtering.FilterConfig`).
        log: the cadences (:class:`nsplat.run.engine.LogConfig`).
    """

    task: str = "refine"
    seed: int = 0
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    scene: SceneConfig = dataclasses.field(default_factory=SceneConfig)
    shading: ShadingConfig = dataclasses.field(default_factory=ShadingConfig)
    poses: PoseConfig = dataclasses.field(default_factory=PoseConfig)
    exposure: ExposureConfig = dataclasses.field(default_factory=ExposureConfig)
    heldout: HeldoutConfig = dataclasses.field(default_factory=HeldoutConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig)
    mask_loss: bool = True
    depth_loss: float = 0.0
    coverage_mask: float = 0.0
    filter: FilterConfig = dataclasses.field(default_factory=FilterConfig)
    log: LogConfig = dataclasses.field(default_factory=LogConfig)

    def __post_init__(self) -> None:
        require(self.task == "refine", "task", "'refine'", self.task)
        require_fields(self, seed=">=0", coverage_mask="unit", depth_loss=">=0")
        if self.render.background is not None and len(self.render.background) != self.scene.channels:
            raise ConfigError(f"render.background: expected {self.scene.channels} values, "
                              f"got {len(self.render.background)}")
        if self.data.source == "rgbd" and self.scene.channels != 3:
            raise ConfigError(f"scene.channels: expected 3 (RGB) for data.source 'rgbd', got {self.scene.channels}")
        if self.shading.model in ("sh", "lambert") and self.scene.channels != 3:
            raise ConfigError(f"shading.model={self.shading.model!r} needs scene.channels = 3")
