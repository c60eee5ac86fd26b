"""Configuration of the ``refine`` task (see :mod:`nsplat.tasks.refine`)."""
from __future__ import annotations

import dataclasses
from typing import Literal

from nsplat.config import ConfigError
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


@dataclasses.dataclass
class ShadingConfig:
    """How albedo becomes colour: ``albedo`` (none), ``sh`` (2nd-order SH irradiance), ``lambert``
    (the paper's camera-fixed lights, :mod:`nsplat.shading`). ``learn_sh`` makes the 9×C SH
    coefficients learnable; ``ambient`` is their initial uniform radiance."""

    model: Literal["albedo", "sh", "lambert"] = "sh"
    learn_sh: bool = True
    ambient: float = 1.0


@dataclasses.dataclass
class PoseConfig:
    """Camera corrections (see :class:`nsplat.tasks.refine.poses.CameraCorrection`)."""

    learn: bool = True
    learn_focal: bool = False
    shared_focal: bool = True
    frozen: list[int] = dataclasses.field(default_factory=list)
    #: rotation pivot of the corrections: ``scene`` (the initial cloud's median depth on each
    #: camera's optical axis; decouples rotation from translation, see :mod:`nsplat.tasks.refine.poses`) or
    #: ``centre`` (the optical centre).
    pivot: Literal["scene", "centre"] = "centre"


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
        bad = [g for g in self.learn if g not in GROUPS]
        if bad:
            raise ConfigError(f"optim.learn: unknown group(s) {bad}; expected names from {list(GROUPS)}")
        bad = [g for g in self.warmup_groups if g not in GROUPS]
        if bad:
            raise ConfigError(f"optim.warmup_groups: unknown group(s) {bad}; expected names from {list(GROUPS)}")
        if self.warmup < 0:
            raise ConfigError(f"optim.warmup: expected >= 0, got {self.warmup}")


#: Optimiser parameter-group names: camera groups, then scene + shading groups.
CAMERA_GROUPS = ("pose", "focal")
GROUPS = CAMERA_GROUPS + ("means", "normals", "scales", "opacities", "features", "sh")


@dataclasses.dataclass
class Config:
    """Configuration of the ``refine`` task."""

    task: str = "refine"
    seed: int = 0
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    scene: SceneConfig = dataclasses.field(default_factory=lambda: SceneConfig(
        channels=3, learn=["means", "normals", "features", "opacities"], opacity=None, scale=None))
    shading: ShadingConfig = dataclasses.field(default_factory=ShadingConfig)
    poses: PoseConfig = dataclasses.field(default_factory=PoseConfig)
    render: RenderConfig = dataclasses.field(default_factory=lambda: RenderConfig(near=0.3, background=[0.0, 0.0, 0.0]))
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig)
    mask_loss: bool = True
    #: also leave out of the loss the pixels where the current render's (detached) alpha is below this
    #: (0: off). Reference pixels that no point covers (parts of the room no keyframe saw) cannot be
    #: explained by any pose; against the background colour they pull every camera towards showing
    #: more of the cloud, a bias of the pose estimate.
    coverage_mask: float = 0.0
    filter: FilterConfig = dataclasses.field(default_factory=FilterConfig)
    log: LogConfig = dataclasses.field(default_factory=lambda: LogConfig(every=10, images=100, validate=0,
                                                                        checkpoint=50))

    def __post_init__(self) -> None:
        if self.task != "refine":
            raise ConfigError(f"task: expected 'refine', got {self.task!r}")
        if self.optim.steps < 0 or self.optim.batch < 1 or self.optim.alternate_every < 1:
            raise ConfigError("optim.steps must be >= 0, optim.batch and optim.alternate_every >= 1")
        if self.render.background is not None and len(self.render.background) != self.scene.channels:
            raise ConfigError(f"render.background: expected {self.scene.channels} values, "
                              f"got {len(self.render.background)}")
        if self.shading.model in ("sh", "lambert") and self.scene.channels != 3:
            raise ConfigError(f"shading.model={self.shading.model!r} needs scene.channels = 3")
