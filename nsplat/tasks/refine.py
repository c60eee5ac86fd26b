"""Task ``refine``: camera-pose and scene refinement against posed RGB frames (paper §4, room scale).

Given reference frames, initial (perturbed) cameras and an initial surfel cloud, minimise the masked
L1 image loss over per-camera SE(3) corrections (:mod:`nsplat.poses`, optional focal), the scene's
learnable attributes (:class:`nsplat.scene.SurfelScene`: positions, normals, scales, opacity, albedo;
each switchable by ``scene.learn``) and the shading (2nd-order SH, :mod:`nsplat.sh`; or plain albedo;
or Lambert with the paper's fixed lights, :mod:`nsplat.shading`). Poses and scene are optimised
jointly or alternately (``optim.schedule``); the outlier filter (:mod:`nsplat.filtering`) removes
points whose accumulated photometric error is improbable.

Data sources: ``room`` (the synthetic benchmark of :mod:`nsplat.data.room`, with ground-truth poses)
and ``nerf`` (NeRF-synthetic frames with ground-truth poses perturbed here, plus an initial cloud read
from a PLY written by :meth:`SurfelScene.save_ply`).

Every render goes through :func:`render_views`, which picks the op (``render.renderer``: the sampled
op ``splat`` or the dense oracle ``splat_dense``); the op's seed is the global step.

Outputs in the run folder: ``tb/`` (TensorBoard), ``checkpoints/`` (atomic, exact resume),
``metrics_initial.json`` / ``metrics_final.json`` (pose errors, masked PSNR/SSIM, point count),
``scene.ply``, ``cameras.pt``, and ``renders/`` from the ``render`` command.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import resource
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from skimage.metrics import structural_similarity
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from nsplat.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from nsplat.config import ConfigError
from nsplat.data.room import RoomSpec, load_room
from nsplat.filtering import FilterConfig, improbable, point_errors
from nsplat.poses import CameraCorrection, perturb_viewmats, pose_errors, pose_report
from nsplat.runctx import RunContext
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.sh import SHLighting
from nsplat.viewer import live
from nsplat.viewer.runs import refine_view

log = logging.getLogger(__name__)
REPO_ROOT = Path(__file__).resolve().parents[2]


# ---------------------------------------------------------------------------------------- config
@dataclasses.dataclass
class NerfSource:
    """NeRF-synthetic frames with perturbed poses and a PLY initial cloud.

    Attributes:
        root: scene folder; empty: ``<repo>/../shared/data/nerf_synthetic/lego_400``.
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
class RenderConfig:
    """The op and its settings (see :func:`nsplat.ops.splat`)."""

    renderer: Literal["splat", "dense"] = "splat"
    samples: int = 40
    eps: float = 0.01
    estimator: Literal["ht", "ht-pips", "paper", "sampled"] = "ht"
    composite: Literal["alpha", "additive"] = "alpha"
    background: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    near: float = 0.3
    far: float = 1e10
    lowpass: float = 1.0


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
    """Camera corrections (see :class:`nsplat.poses.CameraCorrection`)."""

    learn: bool = True
    learn_focal: bool = False
    shared_focal: bool = True
    frozen: list[int] = dataclasses.field(default_factory=list)
    #: rotation pivot of the corrections: ``scene`` (the initial cloud's median depth on each
    #: camera's optical axis; decouples rotation from translation, see :mod:`nsplat.poses`) or
    #: ``centre`` (the optical centre).
    pivot: Literal["scene", "centre"] = "centre"


@dataclasses.dataclass
class LrConfig:
    """Adam learning rates: scene attributes (raw storage units of :class:`SurfelScene`), SH, pose
    twist (metres / radians), log focal."""

    means: float = 1e-3
    normals: float = 1e-2
    scales: float = 1e-2
    opacities: float = 5e-2
    features: float = 1e-2
    sh: float = 1e-2
    pose: float = 1e-3
    focal: float = 1e-4


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
        lr: learning rates.
    """

    steps: int = 300
    batch: int = 4
    schedule: Literal["joint", "alternating"] = "joint"
    alternate_every: int = 10
    warmup: int = 0
    warmup_groups: list[str] = dataclasses.field(default_factory=lambda: ["pose", "focal", "features", "sh"])
    decay_every: int = 0
    decay: float = 0.5
    lr: LrConfig = dataclasses.field(default_factory=LrConfig)

    def __post_init__(self) -> None:
        bad = [g for g in self.warmup_groups if g not in GROUPS]
        if bad:
            raise ConfigError(f"optim.warmup_groups: unknown group(s) {bad}; expected names from {list(GROUPS)}")
        if self.warmup < 0:
            raise ConfigError(f"optim.warmup: expected >= 0, got {self.warmup}")


#: Optimiser parameter-group names: camera groups, then scene + shading groups.
CAMERA_GROUPS = ("pose", "focal")
GROUPS = CAMERA_GROUPS + ("means", "normals", "scales", "opacities", "features", "sh")


@dataclasses.dataclass
class LogConfig:
    """Logging cadence (steps)."""

    every: int = 10
    image_every: int = 100
    checkpoint_every: int = 50


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
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig)
    mask_loss: bool = True
    #: also leave out of the loss the pixels where the current render's (detached) alpha is below this
    #: (0: off). Reference pixels that no point covers (parts of the room no keyframe saw) cannot be
    #: explained by any pose; against the background colour they pull every camera towards showing
    #: more of the cloud, a bias of the pose estimate.
    coverage_mask: float = 0.0
    filter: FilterConfig = dataclasses.field(default_factory=FilterConfig)
    log: LogConfig = dataclasses.field(default_factory=LogConfig)

    def __post_init__(self) -> None:
        if self.task != "refine":
            raise ConfigError(f"task: expected 'refine', got {self.task!r}")
        if self.optim.steps < 0 or self.optim.batch < 1 or self.optim.alternate_every < 1:
            raise ConfigError("optim.steps must be >= 0, optim.batch and optim.alternate_every >= 1")
        if len(self.render.background) != self.scene.channels:
            raise ConfigError(f"render.background: expected {self.scene.channels} values, "
                              f"got {len(self.render.background)}")
        if self.shading.model in ("sh", "lambert") and self.scene.channels != 3:
            raise ConfigError(f"shading.model={self.shading.model!r} needs scene.channels = 3")
        if self.render.samples < 1:
            raise ConfigError(f"render.samples: expected >= 1, got {self.render.samples}")


# ---------------------------------------------------------------------------------------- rendering
def render_views(rcfg: RenderConfig, means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor,
                 opacities: torch.Tensor, features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                 width: int, height: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Render cameras ``[B]`` with the configured op; the only place this task calls an op.

    Args:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]``, opacities ``[N]``: surfels.
        features: ``[N,C]`` (same for every camera) or ``[B,N,C]`` (per camera, rendered one by one).
        viewmats ``[B,4,4]``, Ks ``[B,3,3]``: cameras. seed: the op's sampling seed.

    Returns:
        ``(image [B,H,W,C], alpha [B,H,W,1])``.
    """
    bg = torch.tensor(rcfg.background, dtype=means.dtype, device=means.device)
    if features.shape[-1] != bg.numel():
        bg = bg.new_zeros(features.shape[-1])
    common = dict(composite=rcfg.composite, background=bg, near=rcfg.near, far=rcfg.far, lowpass=rcfg.lowpass)
    if features.dim() == 3:
        outs = [render_views(rcfg, means, normals, scales, opacities, features[b], viewmats[b:b + 1],
                             Ks[b:b + 1], width, height, seed) for b in range(features.shape[0])]
        return torch.cat([o[0] for o in outs]), torch.cat([o[1] for o in outs])
    if rcfg.renderer == "dense":
        from nsplat.ops import splat_dense
        out = splat_dense(means, normals, scales, opacities, features, viewmats, Ks, width, height, **common)
    else:
        try:
            from nsplat.ops import splat
        except ImportError as exc:
            raise ConfigError("render.renderer='splat': the sampled op nsplat.ops.splat is not available "
                              f"({exc}); use render.renderer=dense") from exc
        out = splat(means, normals, scales, opacities, features, viewmats, Ks, width, height,
                    samples=rcfg.samples, eps=rcfg.eps, estimator=rcfg.estimator, seed=int(seed), **common)
    return out.image, out.alpha


# ---------------------------------------------------------------------------------------- data
@dataclasses.dataclass
class Frames:
    """Reference frames and cameras: ``images [B,H,W,C]``, ``masks [B,H,W]`` bool, initial
    ``viewmats [B,4,4]``, ``Ks [B,3,3]``, ground truth ``viewmats_gt`` (or ``None``)."""

    images: torch.Tensor
    masks: torch.Tensor
    viewmats: torch.Tensor
    Ks: torch.Tensor
    viewmats_gt: torch.Tensor | None

    @property
    def count(self) -> int:
        return int(self.images.shape[0])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])


def _resolve(path: str) -> Path:
    p = Path(path)
    return p if p.is_absolute() else REPO_ROOT / p


def load_data(cfg: Config, device: torch.device) -> tuple[Frames, SurfelScene]:
    """Frames and the initial scene of ``cfg.data`` (on ``device``)."""
    d = cfg.data
    if d.source == "room":
        room = load_room(d.room, _resolve(d.cache_dir))
        frames = Frames(room.images, room.masks, room.viewmats_init, room.Ks, room.viewmats)
        n = room.means.shape[0]
        scene = SurfelScene.from_points(cfg.scene, room.means, room.normals,
                                        scales=room.scales[:, None].expand(n, 2).contiguous(),
                                        opacities=torch.full((n,), d.init_opacity), features=room.colours)
    else:
        from nsplat.data.nerf_synthetic import load_split
        nf = d.nerf
        root = Path(nf.root) if nf.root else REPO_ROOT.parent / "shared" / "data" / "nerf_synthetic" / "lego_400"
        views = load_split(root, nf.split, resolution=nf.resolution,
                           background=cfg.render.background if cfg.scene.channels == 3 else (1.0, 1.0, 1.0),
                           limit=nf.limit or None)
        if not nf.cloud:
            raise ConfigError("data.nerf.cloud: a PLY initial cloud is required for source 'nerf'")
        scene = SurfelScene.load_ply(_resolve(nf.cloud), cfg.scene)
        extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
        g = torch.Generator().manual_seed(nf.perturb_seed)
        init = perturb_viewmats(views.viewmats, nf.rot_deg, nf.trans_frac * extent, generator=g)
        masks = torch.ones(views.images.shape[:3], dtype=torch.bool)
        frames = Frames(views.images, masks, init.float(), views.Ks.float(), views.viewmats.float())
    frames = Frames(**{f.name: (None if getattr(frames, f.name) is None else getattr(frames, f.name).to(device))
                       for f in dataclasses.fields(frames)})
    return frames, scene.to(device)


# ---------------------------------------------------------------------------------------- model
def scene_pivots(means: torch.Tensor, viewmats: torch.Tensor, near: float = 1e-3) -> torch.Tensor:
    """``[B, 3]`` pivots ``(0, 0, d_b)`` in camera coordinates: ``d_b`` the median depth of the points
    of ``means [N,3]`` in front of camera ``b`` and inside its 90° cone (1 when none are)."""
    cam = torch.einsum("bij,nj->bni", viewmats[:, :3, :3].to(means), means) + viewmats[:, None, :3, 3].to(means)
    z = cam[..., 2]
    ok = (z > near) & (cam[..., :2].norm(dim=-1) < z)
    out = torch.zeros(viewmats.shape[0], 3, dtype=means.dtype, device=means.device)
    for b in range(viewmats.shape[0]):
        out[b, 2] = z[b][ok[b]].median() if bool(ok[b].any()) else 1.0
    return out


class Refiner(torch.nn.Module):
    """Scene + shading + camera corrections; produces rendered views of camera indices."""

    def __init__(self, cfg: Config, scene: SurfelScene, frames: Frames) -> None:
        super().__init__()
        self.cfg = cfg
        self.scene = scene
        self.frames = frames
        self.sh = (SHLighting(cfg.scene.channels, cfg.shading.ambient, learnable=cfg.shading.learn_sh)
                   if cfg.shading.model == "sh" else None)
        p = cfg.poses
        pivots = scene_pivots(scene.means.detach(), frames.viewmats) if p.pivot == "scene" else None
        self.cameras = (CameraCorrection(frames.count, learn_pose=p.learn, learn_focal=p.learn_focal,
                                         shared_focal=p.shared_focal, frozen=p.frozen, pivots=pivots)
                        if (p.learn or p.learn_focal) else None)

    def camera(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected ``(viewmats [b,4,4], Ks [b,3,3])`` of cameras ``index [b]``."""
        V, K = self.frames.viewmats[index], self.frames.Ks[index]
        if self.cameras is None:
            return V, K
        return self.cameras(V, K, index)

    def colours(self, viewmats: torch.Tensor) -> torch.Tensor:
        """Shaded point colours: ``[N,C]`` (albedo, SH) or ``[b,N,C]`` (Lambert, per camera)."""
        s = self.scene
        if self.cfg.shading.model == "sh":
            return self.sh(s.features, s.normals)
        if self.cfg.shading.model == "lambert":
            from nsplat.shading import lambert
            return lambert(s.features, s.normals, viewmats)
        return s.features

    def forward(self, index: torch.Tensor, seed: int, features: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Render cameras ``index [b]``: ``(image [b,H,W,C], alpha [b,H,W,1])``. ``features`` overrides
        the shaded colours (used by the outlier filter's probe)."""
        V, K = self.camera(index)
        s = self.scene
        f = self.colours(V) if features is None else features
        return render_views(self.cfg.render, s.means, s.normals, s.scales, s.opacities, f, V, K,
                            self.frames.width, self.frames.height, seed)

    def pose_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.cameras is None else [p for p in (self.cameras.twist,) if p is not None]

    def focal_parameters(self) -> list[torch.nn.Parameter]:
        return [] if self.cameras is None or self.cameras.log_focal is None else [self.cameras.log_focal]


def _optimizers(model: Refiner, cfg: Config) -> dict[str, torch.optim.Optimizer]:
    lr = cfg.optim.lr
    out: dict[str, torch.optim.Optimizer] = {}
    cam_groups = []
    if model.pose_parameters():
        cam_groups.append({"params": model.pose_parameters(), "lr": lr.pose, "name": "pose"})
    if model.focal_parameters():
        cam_groups.append({"params": model.focal_parameters(), "lr": lr.focal, "name": "focal"})
    if cam_groups:
        out["camera"] = torch.optim.Adam(cam_groups)
    scene_groups = model.scene.param_groups({k: getattr(lr, k) for k in
                                             ("means", "normals", "scales", "opacities", "features")})
    if model.sh is not None and cfg.shading.learn_sh:
        scene_groups.append({"params": [model.sh.coeffs], "lr": lr.sh, "name": "sh"})
    if scene_groups:
        out["scene"] = torch.optim.Adam(scene_groups)
    for opt in out.values():
        for g in opt.param_groups:
            g["initial_lr"] = g["lr"]
    return out


def _set_lr(opts: dict[str, torch.optim.Optimizer], cfg: Config, step: int) -> None:
    o = cfg.optim
    f = o.decay ** (max(0, step - o.warmup) // o.decay_every) if o.decay_every > 0 else 1.0
    for opt in opts.values():
        for g in opt.param_groups:
            g["lr"] = g["initial_lr"] * f


def _active(cfg: Config, step: int) -> set[str]:
    """Parameter-group names updated at ``step`` (warm-up, then the joint or alternating schedule)."""
    o = cfg.optim
    if step < o.warmup:
        return set(o.warmup_groups)
    if o.schedule == "joint":
        return set(GROUPS)
    k = step - o.warmup
    camera_phase = (k // o.alternate_every) % 2 == 0
    return set(CAMERA_GROUPS) if camera_phase else set(GROUPS) - set(CAMERA_GROUPS)


def _step_active(opts: dict[str, torch.optim.Optimizer], active: set[str]) -> None:
    """Adam steps of the active groups only (inactive groups' gradients are dropped, so Adam leaves
    their values and moments untouched)."""
    for opt in opts.values():
        any_active = False
        for g in opt.param_groups:
            if g["name"] in active:
                any_active = True
            else:
                for p in g["params"]:
                    p.grad = None
        if any_active:
            opt.step()


def _prune(model: Refiner, keep: torch.Tensor, opts: dict[str, torch.optim.Optimizer]) -> None:
    """Keep only points ``keep [N]`` (bool): a new :class:`SurfelScene` and its Adam state sliced."""
    old = model.scene
    params = {name: old.tensor(name) for name in old.cfg.learn}
    new = SurfelScene(old.cfg, int(keep.sum()), dtype=old.means.dtype, device=old.means.device)
    new.load_state_dict({k: v[keep] for k, v in old.state_dict().items()})
    model.scene = new
    opt = opts.get("scene")
    if opt is None:
        return
    for g in opt.param_groups:
        if g.get("name") in params:
            p_old = g["params"][0]
            p_new = new.tensor(g["name"])
            st = opt.state.pop(p_old, None)
            if st:
                opt.state[p_new] = {k: (v[keep] if isinstance(v, torch.Tensor) and v.shape == p_old.shape else v)
                                    for k, v in st.items()}
            g["params"] = [p_new]


def _masked_l1(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask[..., None].to(img.dtype)
    return ((img - ref).abs() * m).sum() / (m.sum() * img.shape[-1]).clamp_min(1.0)


# ---------------------------------------------------------------------------------------- metrics
def image_metrics(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> tuple[float, float]:
    """Masked PSNR and SSIM of one image ``[H,W,C]`` in [0,1] against ``ref`` (``mask [H,W]``).

    SSIM is scikit-image's (Gaussian window σ = 1.5, data range 1) map averaged over valid pixels.
    """
    a = img.detach().clamp(0, 1).cpu().double().numpy()
    b = ref.detach().cpu().double().numpy()
    m = mask.detach().cpu().numpy().astype(bool)
    mse = float(((a - b) ** 2)[m].mean())
    psnr = 10.0 * math.log10(1.0 / max(mse, 1e-12))
    _, smap = structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                    sigma=1.5, use_sample_covariance=False, full=True)
    return psnr, float(smap.mean(-1)[m].mean())


@torch.no_grad()
def evaluate_state(model: Refiner, seed: int, batch: int) -> tuple[dict[str, Any], torch.Tensor]:
    """Pose errors and masked PSNR/SSIM over all frames; returns ``(metrics, renders [B,H,W,C])``."""
    fr = model.frames
    renders = []
    for s in range(0, fr.count, batch):
        idx = torch.arange(s, min(s + batch, fr.count), device=fr.images.device)
        renders.append(model(idx, seed)[0])
    img = torch.cat(renders)
    ps, ss = zip(*(image_metrics(img[b], fr.images[b], fr.masks[b]) for b in range(fr.count)))
    out: dict[str, Any] = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)),
                           "points": model.scene.num_points}
    if fr.viewmats_gt is not None:
        V, K = model.camera(torch.arange(fr.count, device=fr.images.device))
        out.update(pose_report(V, fr.viewmats_gt))
        if model.cameras is not None and model.cameras.log_focal is not None:
            out["focal_scale"] = torch.exp(model.cameras.log_focal).tolist()
    return out, img


# ---------------------------------------------------------------------------------------- filter
@torch.no_grad()
def run_filter(model: Refiner, cfg: Config, seed: int) -> torch.Tensor:
    """Accumulate per-point photometric error over all frames; returns the outlier mask ``[N]``."""
    fr = model.frames
    N = model.scene.num_points
    E = torch.zeros(N, dtype=torch.float64, device=fr.images.device)
    W = torch.zeros_like(E)
    # per-camera colours (Lambert) need one camera per probe render
    step = 1 if cfg.shading.model == "lambert" else cfg.optim.batch
    for s in range(0, fr.count, step):
        idx = torch.arange(s, min(s + step, fr.count), device=fr.images.device)
        V, _ = model.camera(idx)
        colours = model.colours(V)
        colours = colours[0] if colours.dim() == 3 else colours
        mask = fr.masks[idx] if cfg.mask_loss else None
        e, w = point_errors(lambda f: model(idx, seed, features=f)[0], colours, fr.images[idx], mask)
        E += e.double()
        W += w.double()
    return improbable(E, W, cfg.filter)


# ---------------------------------------------------------------------------------------- run
def _batch(cfg: Config, count: int, step: int, seed: int) -> torch.Tensor:
    """Views of ``step``: epochs of a seeded permutation (a function of the step: exact resume)."""
    per_epoch = max(1, math.ceil(count / cfg.optim.batch))
    epoch, k = divmod(step, per_epoch)
    perm = torch.randperm(count, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))
    sel = perm[k * cfg.optim.batch:(k + 1) * cfg.optim.batch]
    return sel if sel.numel() else perm[:cfg.optim.batch]


def _save_outputs(model: Refiner, ctx: RunContext) -> None:
    model.scene.save_ply(ctx.run_dir / "scene.ply")
    V, K = model.camera(torch.arange(model.frames.count, device=model.frames.images.device))
    torch.save({"viewmats": V.detach().cpu(), "Ks": K.detach().cpu(),
                "sh": None if model.sh is None else model.sh.coeffs.detach().cpu()}, ctx.run_dir / "cameras.pt")


def build(cfg: Config, ctx: RunContext) -> tuple[Refiner, dict[str, torch.optim.Optimizer], int, dict[str, Any]]:
    """Model and optimisers, restored from the run's latest checkpoint when ``ctx.resume``."""
    frames, scene = load_data(cfg, ctx.device)
    model = Refiner(cfg, scene, frames).to(ctx.device)
    step, extra = 0, {}
    if ctx.resume:
        ck = load_checkpoint(ctx.run_dir, map_location=ctx.device)
        model.scene = SurfelScene(cfg.scene, int(ck["num_points"]), device=ctx.device)
        model.load_state_dict(ck["model"])
        opts = _optimizers(model, cfg)
        for k, opt in opts.items():
            opt.load_state_dict(ck["optim"][k])
        step, extra = int(ck["step"]), ck.get("extra", {})
    else:
        opts = _optimizers(model, cfg)
    return model, opts, step, extra


def run(cfg: Config, ctx: RunContext) -> dict[str, Any]:
    """Refine; returns the final metrics (also written to ``metrics_final.json``)."""
    torch.manual_seed(ctx.seed)
    model, opts, step, extra = build(cfg, ctx)
    fr = model.frames
    writer = SummaryWriter(str(ctx.run_dir / "tb"), purge_step=step if ctx.resume else None)
    if step == 0:
        init, img0 = evaluate_state(model, ctx.seed, cfg.optim.batch)
        (ctx.run_dir / "metrics_initial.json").write_text(json.dumps(init, indent=1))
        torch.save(img0.cpu(), ctx.run_dir / "renders_initial.pt")
        log.info("initial: %s", init)
        extra = {"initial": init, "seconds": 0.0, "removed": 0}
    t_start = time.perf_counter() - float(extra.get("seconds", 0.0))
    bar = tqdm(range(step, cfg.optim.steps), initial=step, total=cfg.optim.steps, desc="refine")
    for step in bar:
        _set_lr(opts, cfg, step)
        idx = _batch(cfg, fr.count, step, ctx.seed).to(ctx.device)
        active = _active(cfg, step)
        for opt in opts.values():
            opt.zero_grad(set_to_none=True)
        img, alpha = model(idx, seed=ctx.seed * 1_000_003 + step)
        mask = fr.masks[idx] if cfg.mask_loss else torch.ones_like(fr.masks[idx])
        if cfg.coverage_mask > 0:
            mask = mask & (alpha.detach()[..., 0] >= cfg.coverage_mask)
        loss = _masked_l1(img, fr.images[idx], mask)
        loss.backward()
        _step_active(opts, active)
        done = step + 1
        live.step(done, lambda: refine_view(model, ctx.seed))
        if cfg.filter.due(done):
            bad = run_filter(model, cfg, seed=ctx.seed * 1_000_003 + done)
            if bool(bad.any()):
                _prune(model, ~bad, opts)
                extra["removed"] = int(extra.get("removed", 0)) + int(bad.sum())
                log.info("step %d: outlier filter removed %d points (%d left)", done, int(bad.sum()),
                         model.scene.num_points)
        if done % cfg.log.every == 0 or done == cfg.optim.steps:
            writer.add_scalar("loss/l1", float(loss.detach()), done)
            writer.add_scalar("scene/points", model.scene.num_points, done)
            if fr.viewmats_gt is not None:
                V, _ = model.camera(torch.arange(fr.count, device=ctx.device))
                rot, tr = pose_errors(V, fr.viewmats_gt)
                writer.add_scalar("pose/rot_deg", float(rot.mean()), done)
                writer.add_scalar("pose/trans", float(tr.mean()), done)
                log.debug("step %d: loss %.5f rot %.4f° trans %.5f", done, float(loss.detach()),
                          float(rot.mean()), float(tr.mean()))
                bar.set_postfix(loss=f"{float(loss.detach()):.4f}", rot=f"{float(rot.mean()):.3f}",
                                tr=f"{float(tr.mean()):.4f}", n=model.scene.num_points)
        if cfg.log.image_every and done % cfg.log.image_every == 0:
            writer.add_images("render", img[:1].detach().clamp(0, 1), done, dataformats="NHWC")
        if done % cfg.log.checkpoint_every == 0 or done == cfg.optim.steps:
            extra["seconds"] = time.perf_counter() - t_start
            save_checkpoint(ctx.run_dir, done, {
                "model": model.state_dict(), "num_points": model.scene.num_points,
                "optim": {k: o.state_dict() for k, o in opts.items()}, "extra": extra})
    seconds = time.perf_counter() - t_start
    final, img = evaluate_state(model, ctx.seed, cfg.optim.batch)
    final.update(seconds=seconds, removed=int(extra.get("removed", 0)), steps=cfg.optim.steps,
                 peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    (ctx.run_dir / "metrics_final.json").write_text(json.dumps(final, indent=1))
    torch.save(img.cpu(), ctx.run_dir / "renders_final.pt")
    _save_outputs(model, ctx)
    for k, v in final.items():
        if isinstance(v, (int, float)):
            writer.add_scalar(f"final/{k}", v, cfg.optim.steps)
    writer.close()
    log.info("final: %s", final)
    return final


def evaluate(cfg: Config, ctx: RunContext, split: str = "train") -> dict[str, Any]:
    """Metrics of the run's latest checkpoint (the refined frames; ``split`` is not used: refinement
    is scored on the frames it refines). Written to ``eval.json``."""
    model, _, step, _ = build(cfg, dataclasses.replace(ctx, resume=True))
    out, _ = evaluate_state(model, ctx.seed, cfg.optim.batch)
    out["step"] = step
    (ctx.run_dir / "eval.json").write_text(json.dumps(out, indent=1))
    log.info("eval: %s", out)
    return out


def render(cfg: Config, ctx: RunContext) -> None:
    """Write reference | render | |difference| PNGs of every frame to ``renders/``."""
    import imageio.v3 as iio
    model, _, _, _ = build(cfg, dataclasses.replace(ctx, resume=True))
    _, img = evaluate_state(model, ctx.seed, cfg.optim.batch)
    out = ctx.run_dir / "renders"
    out.mkdir(exist_ok=True)
    for b in range(img.shape[0]):
        ref = model.frames.images[b]
        row = torch.cat([ref, img[b].clamp(0, 1), (img[b] - ref).abs().clamp(0, 1)], 1)
        iio.imwrite(out / f"{b:03d}.png", (row.cpu().numpy() * 255).round().astype(np.uint8))
