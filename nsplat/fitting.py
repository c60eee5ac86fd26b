"""The generic surfel fitter: a :class:`~nsplat.scene.SurfelScene` fitted to posed images (paper §4).

Used by the shape task (:mod:`nsplat.tasks.reconstruct`) and by stage 1 of the neural task. Renders go
through the gateway :mod:`nsplat.render`.

* :func:`point_contributions` — per-point visual contribution (weight × colour) over a set of views.
* :func:`reposition` — moves non-contributing points next to random visible ones (tangent jitter).
* :func:`fit` — Adam on an L1 image loss with a step-halving schedule, per-epoch repositioning,
  TensorBoard logging, atomic checkpoints and exact resume.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Callable, Literal

import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from nsplat.config import require_fields
from nsplat.checkpoint import CheckpointError, NoCheckpoint, load_checkpoint, save_checkpoint
from nsplat.ops import tangent_frame
from nsplat.render import RenderConfig, render, render_views
from nsplat.scene import SurfelScene
from nsplat.shading import lambert
from nsplat.viewer import live
from nsplat.viewer.runs import cameras_of, surfel_view

log = logging.getLogger(__name__)


def point_contributions(scene: SurfelScene, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                        cfg: RenderConfig, *, seed: int = 0, chunk: int = 12,
                        measure: Literal["radiance", "weight"] = "radiance",
                        shading: Literal["lambert", "none"] = "lambert") -> torch.Tensor:
    """Per-point visual contribution summed over views: ``[N]`` (no gradient).

    ``measure="weight"``: ``Σ_views Σ_x w_k(x)`` (total compositing weight). ``measure="radiance"``:
    ``Σ_views Σ_x w_k(x) · ‖c_k‖`` with ``c_k`` the point's (shaded, per camera) colour, so a visible but
    black point — e.g. an outlier that learned to vanish against the black background — counts as
    contributing nothing. Computed as the gradient of the summed one-channel image w.r.t. a unit probe
    (``∂I(x)/∂f_k = w_k(x)``); with the sampled op it is the Horvitz–Thompson estimate (estimator
    ``ht``), zero exactly for points never sampled with non-zero weight.
    """
    with torch.no_grad():
        geo = (scene.means.detach(), scene.normals.detach(), scene.scales.detach(), scene.opacities.detach())
        feats = scene.features.detach()
    N, dtype, device = scene.num_points, geo[0].dtype, geo[0].device
    total = torch.zeros(N, dtype=dtype, device=device)
    per_camera = measure == "radiance" and shading == "lambert"
    step = 1 if per_camera else chunk
    for s in range(0, viewmats.shape[0], step):
        vm, K = viewmats[s:s + step], Ks[s:s + step]
        if measure == "weight":
            colour = torch.ones(N, dtype=dtype, device=device)
        elif per_camera:
            colour = lambert(feats, geo[1], vm)[0].norm(dim=-1)
        else:
            colour = feats.norm(dim=-1)
        probe = torch.ones(N, 1, dtype=dtype, device=device, requires_grad=True)
        out = render(*geo, probe * colour[:, None], vm, K, width, height, cfg, seed=seed + s, estimator="ht")
        (grad,) = torch.autograd.grad(out.image.sum(), probe)
        total += grad[:, 0]
    return total


@torch.no_grad()
def reposition(scene: SurfelScene, contributions: torch.Tensor, min_weight: float, jitter: float,
               generator: torch.Generator, optimizer: torch.optim.Optimizer | None = None) -> int:
    """Move every point with ``contributions < min_weight`` next to a random visible point.

    The moved point copies the chosen point's normal, scales, opacity and features and is placed at
    its position plus a Gaussian offset in its tangent plane with std-dev ``jitter × scale`` per axis.
    The moved rows' Adam state is reset. Returns the number of moved points (0 when none is visible).
    """
    dead = (contributions < min_weight).nonzero().squeeze(1)
    alive = (contributions >= min_weight).nonzero().squeeze(1)
    if dead.numel() == 0 or alive.numel() == 0:
        return 0
    pick = alive[torch.randint(alive.numel(), (dead.numel(),), generator=generator).to(alive.device)]
    normals = scene.normals[pick]
    scales = scene.scales[pick]
    t0, t1 = tangent_frame(normals)
    z = torch.randn(dead.numel(), 2, generator=generator).to(normals) * jitter * scales
    values = {"means": scene.means[pick] + z[:, :1] * t0 + z[:, 1:] * t1, "normals": normals,
              "features": scene.features[pick]}
    if scene.cfg.scale is None:
        values["scales"] = scales
    if scene.cfg.opacity is None:
        values["opacities"] = scene.opacities[pick]
    scene.replace(dead, values, optimizer)
    return int(dead.numel())


@dataclasses.dataclass
class FitConfig:
    """Optimisation settings (defaults: the paper's).

    Attributes:
        epochs: passes over all views. batch: views per step.
        lr: learning rate of every learnable attribute unless overridden in ``lrs``.
        lrs: per-attribute learning rates (``means``, ``normals``, ``scales``, ``opacities``, ``features``).
        lr_decays: number of times the rate is multiplied by ``lr_gamma``, at regular intervals.
        betas: Adam decay rates.
        shading: ``lambert`` (features are albedo, shaded per camera) or ``none`` (features rendered as is).
        reposition: move non-contributing points after every ``reposition_every``-th epoch (paper: every
            epoch; each check renders all views once more, so CPU runs may space it out).
            contribution: what "contributes" means (:func:`point_contributions`): ``radiance`` (weight ×
            colour, the paper's "visual contribution", default) or ``weight``. min_weight: a point contributes when
            its contribution summed over all views is at least this. jitter: tangent offset of a moved
            point, in units of its source point's scale.
        checkpoint_every: epochs between checkpoints (the last epoch is always saved).
    """

    epochs: int = 300
    batch: int = 12
    lr: float = 0.01
    lrs: dict[str, float] = dataclasses.field(default_factory=dict)
    lr_decays: int = 5
    lr_gamma: float = 0.5
    betas: tuple[float, float] = (0.9, 0.999)
    shading: Literal["lambert", "none"] = "lambert"
    reposition: bool = True
    reposition_every: int = 1
    contribution: Literal["radiance", "weight"] = "radiance"
    min_weight: float = 0.02
    jitter: float = 1.0
    checkpoint_every: int = 1

    def milestones(self) -> list[int]:
        """Epochs at which the rate is decayed: ``round(k·epochs/(lr_decays+1))``, k = 1..lr_decays."""
        return [round(k * self.epochs / (self.lr_decays + 1)) for k in range(1, self.lr_decays + 1)]

    def __post_init__(self) -> None:
        require_fields(self, epochs=">=0", batch=">=1", lr=">0", lr_decays=">=0", lr_gamma=">0",
                       reposition_every=">=1", min_weight=">=0", jitter=">=0", checkpoint_every=">=1")


EpochCallback = Callable[[int, SurfelScene, SummaryWriter], dict[str, float]]


def fit(scene: SurfelScene, images: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, cfg: FitConfig,
        render_cfg: RenderConfig, run_dir: str | Path, *, seed: int = 0, resume: bool = False,
        background: torch.Tensor | None = None, on_epoch: EpochCallback | None = None,
        progress: bool = True) -> dict[str, float]:
    """Optimise ``scene`` in place so its renders match ``images``.

    Args:
        scene: the surfels; its learnable attributes are optimised.
        images: ``[V,H,W,C]`` target images. viewmats ``[V,4,4]``, Ks ``[V,3,3]``: their cameras.
        cfg: optimisation settings. render_cfg: renderer (op seed = ``seed·10⁶ + step·batch``).
        run_dir: TensorBoard logs go to ``run_dir/tb``, checkpoints to ``run_dir/checkpoints``.
        resume: continue from the last checkpoint in ``run_dir`` (bit-exact on the same machine).
        on_epoch: optional ``f(epoch, scene, writer) -> scalars`` run after each epoch (e.g. metrics).

    Returns:
        the last epoch's scalars (``loss``, ``moved``, ``lr`` and ``on_epoch``'s).
    """
    V, H, W, C = images.shape
    if viewmats.shape != (V, 4, 4) or Ks.shape != (V, 3, 3):
        raise ValueError(f"viewmats/Ks: expected [{V},4,4]/[{V},3,3] for {V} images, "
                         f"got {list(viewmats.shape)}/{list(Ks.shape)}")
    for key in ("batch", "epochs", "reposition_every", "checkpoint_every"):
        if getattr(cfg, key) < 1:
            raise ValueError(f"optim.{key}: expected >= 1, got {getattr(cfg, key)}")
    run_dir = Path(run_dir)
    lrs = {"default": cfg.lr, **cfg.lrs}
    optimizer = torch.optim.Adam(scene.param_groups(lrs), betas=tuple(cfg.betas))
    steps_per_epoch = math.ceil(V / cfg.batch)
    scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, cfg.milestones(), gamma=cfg.lr_gamma)
    gen = torch.Generator().manual_seed(seed)
    epoch0, step = 0, 0
    scalars: dict[str, float] = {}
    if resume:
        try:
            state = load_checkpoint(run_dir)
        except NoCheckpoint:
            log.info("no checkpoint in %s; starting from scratch", run_dir)
        else:
            scene.load_state_dict(state["scene"])
            optimizer.load_state_dict(state["optimizer"])
            scheduler.load_state_dict(state["scheduler"])
            gen.set_state(state["generator"])
            epoch0, step = state["epoch"], state["step"]
            scalars = dict(state.get("scalars", {}))
            log.info("resumed from epoch %d (step %d)", epoch0, step)
    writer = SummaryWriter(str(run_dir / "tb"), purge_step=step if step else None)
    bar = tqdm(total=cfg.epochs * steps_per_epoch, initial=epoch0 * steps_per_epoch, disable=not progress,
               desc="fit", dynamic_ncols=True)
    cams = cameras_of(images, viewmats, Ks)
    try:
        for epoch in range(epoch0, cfg.epochs):
            perm = torch.randperm(V, generator=gen)
            epoch_loss = 0.0
            for s in range(steps_per_epoch):
                idx = perm[s * cfg.batch:(s + 1) * cfg.batch]
                optimizer.zero_grad(set_to_none=True)
                loss_val = 0.0
                # Backward per view: memory stays at one view's graph; gradients are summed.
                for j, v in enumerate(idx.tolist()):
                    img = render_views(scene, viewmats[v:v + 1], Ks[v:v + 1], W, H, render_cfg,
                                       seed=seed * 1_000_000 + step * cfg.batch + j, shading=cfg.shading,
                                       background=background)
                    loss = (img - images[v:v + 1]).abs().mean() / idx.numel()
                    loss.backward()
                    loss_val += loss.item()
                optimizer.step()
                writer.add_scalar("train/loss", loss_val, step)
                epoch_loss += loss_val / steps_per_epoch
                step += 1
                bar.update(1)
                bar.set_postfix(epoch=epoch, loss=f"{loss_val:.4f}")
                live.step(step, lambda: surfel_view(scene, cams, shading=cfg.shading, background=background,
                                                    render_cfg=render_cfg, task="fit", seed=seed))
            moved = 0
            if cfg.reposition and (epoch + 1) % cfg.reposition_every == 0:
                contrib = point_contributions(scene, viewmats, Ks, W, H, render_cfg, seed=seed * 1_000_000 + step,
                                              chunk=cfg.batch, measure=cfg.contribution, shading=cfg.shading)
                moved = reposition(scene, contrib, cfg.min_weight, cfg.jitter, gen, optimizer)
            scheduler.step()
            scalars = {"loss": epoch_loss, "moved": float(moved), "lr": optimizer.param_groups[0]["lr"]}
            if on_epoch is not None:
                scalars.update(on_epoch(epoch, scene, writer))
            for k, v in scalars.items():
                writer.add_scalar(f"epoch/{k}", v, step)
            log.debug("epoch %d: %s", epoch, scalars)
            last = epoch + 1 == cfg.epochs
            if last or (epoch + 1) % cfg.checkpoint_every == 0:
                save_checkpoint(run_dir, step, {"scene": scene.state_dict(), "optimizer": optimizer.state_dict(),
                                                "scheduler": scheduler.state_dict(), "generator": gen.get_state(),
                                                "epoch": epoch + 1, "scalars": scalars})
    finally:
        bar.close()
        writer.close()
    return scalars
