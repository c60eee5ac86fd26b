"""Configuration of the ``refine`` task (see :mod:`nsplat.tasks.refine`)."""
from __future__ import annotations

import dataclasses
from typing import Literal

from nsplat.config import ConfigError, require, require_fields
from nsplat.data.room import RoomSpec
from nsplat.engine import LogConfig
from nsplat.render import RenderConfig
from nsplat.scene import SceneConfig
from nsplat.tasks.refine.filtering import FilterConfig


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
class DataConfig:
    """Where frames, cameras and the initial cloud come from.

    Attributes:
        source: ``room`` (synthetic benchmark) or ``nerf`` (NeRF-synthetic + PLY cloud).
        room: the room benchmark's settings.
        nerf: the NeRF-synthetic settings.
        cache_dir: cache folder (relative to the repository root unless absolute).
        init_opacity: initial opacity of the cloud's points (where opacity is per point).
    """

    source: Literal["room", "nerf"] = "room"
    room: RoomSpec = dataclasses.field(default_factory=RoomSpec)
    nerf: NerfSource = dataclasses.field(default_factory=NerfSource)
    cache_dir: str = "data_cache"
    init_opacity: float = 0.9

    def __post_init__(self) -> None:
        require_fields(self, init_opacity="open")


@dataclasses.dataclass
class ShadingConfig:
    """How albedo becomes colour.

    Attributes:
        model: ``albedo`` (none), ``sh`` (2nd-order SH irradiance) or ``lambert`` (the paper's camera-fixed
            lights, :mod:`nsplat.shading`).
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
    """

    learn: bool = True
    learn_focal: bool = False
    shared_focal: bool = True
    frozen: list[int] = dataclasses.field(default_factory=list)
    pivot: Literal["scene", "centre"] = "centre"

    def __post_init__(self) -> None:
        require_fields(self, frozen=">=0")


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
            (twist: metres / radians) and ``focal`` (log focal).
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
        "pose": 1e-3, "focal": 1e-4})

    def __post_init__(self) -> None:
        require(all(g in GROUPS and v > 0 for g, v in self.learn.items()), "learn",
                f"positive rates for groups among {list(GROUPS)}", self.learn)
        require(all(g in GROUPS for g in self.warmup_groups), "warmup_groups", f"names from {list(GROUPS)}",
                self.warmup_groups)
        require_fields(self, steps=">=0", batch=">=1", alternate_every=">=1", warmup=">=0", decay_every=">=0",
                       decay="prob")


#: Optimiser parameter-group names: camera groups, then scene + shading groups.
CAMERA_GROUPS = ("pose", "focal")
GROUPS = CAMERA_GROUPS + ("means", "normals", "scales", "opacities", "features", "sh")


@dataclasses.dataclass
class Config:
    """Configuration of the ``refine`` task.

    Attributes:
        task: ``refine``. seed: the run seed (batch order, every op seed).
        data: :class:`DataConfig`, frames, cameras and the initial cloud. scene: which point attributes exist
            and are learned (:class:`nsplat.scene.SceneConfig`). shading: :class:`ShadingConfig`.
        poses: :class:`PoseConfig`. render: the render settings (:class:`nsplat.render.RenderConfig`).
        optim: :class:`OptimConfig`. mask_loss: restrict the loss to the frames' valid pixels.
        coverage_mask: also leave out of the loss the pixels where the current render's (detached) alpha is
            below this, in [0, 1] (0: off). Reference pixels that no point covers (parts of the room no keyframe
            saw) cannot be explained by any pose; against the background colour they pull every camera towards
            showing more of the cloud, a bias of the pose estimate.
        filter: the outlier filter (:class:`nsplat.tasks.refine.filtering.FilterConfig`).
        log: the cadences (:class:`nsplat.engine.LogConfig`).
    """

    task: str = "refine"
    seed: int = 0
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    scene: SceneConfig = dataclasses.field(default_factory=SceneConfig)
    shading: ShadingConfig = dataclasses.field(default_factory=ShadingConfig)
    poses: PoseConfig = dataclasses.field(default_factory=PoseConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig)
    mask_loss: bool = True
    coverage_mask: float = 0.0
    filter: FilterConfig = dataclasses.field(default_factory=FilterConfig)
    log: LogConfig = dataclasses.field(default_factory=LogConfig)

    def __post_init__(self) -> None:
        require(self.task == "refine", "task", "'refine'", self.task)
        require_fields(self, seed=">=0", coverage_mask="unit")
        if self.render.background is not None and len(self.render.background) != self.scene.channels:
            raise ConfigError(f"render.background: expected {self.scene.channels} values, "
                              f"got {len(self.render.background)}")
        if self.shading.model in ("sh", "lambert") and self.scene.channels != 3:
            raise ConfigError(f"shading.model={self.shading.model!r} needs scene.channels = 3")
