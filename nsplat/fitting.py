"""The generic surfel fitter: a :class:`~nsplat.scene.SurfelScene` fitted to posed images (paper §4).

Used by the shape task (:mod:`nsplat.tasks.reconstruct`) and by stage 1 of the neural task. Renders go
through the gateway :mod:`nsplat.render`.

* :func:`point_contributions` — per-point visual contribution (weight × colour) over a set of views.
* :func:`reposition` — moves non-contributing points next to random visible ones (tangent jitter).
* :func:`fit` — Adam on an L1 image loss with a step-halving schedule, per-epoch repositioning and
  optional adaptive density control (:mod:`nsplat.densify`), run by the engine (:mod:`nsplat.engine`:
  logging, atomic checkpoints, exact resume — also across changes of the point count). Data-parallel
  under torchrun (:mod:`nsplat.distributed`): each rank renders its share of a step's views and of the
  repositioning's contribution renders; gradients, contributions and densification statistics are
  summed over ranks, so every rank takes the same decisions.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Literal

import torch

from nsplat import distributed
from nsplat.config import ConfigError, require, require_fields
from nsplat.data.views import PosedViews
from nsplat.densify import DensifyConfig, DensityStats, densify
from nsplat.engine import Engine, Hook, LogConfig, Trainables, checkpoint_rows, generator, latest_payload, op_seed
from nsplat.losses import dssim_loss
from nsplat.ops import tangent_frame
from nsplat.points import reset_rows
from nsplat.render import RenderConfig, render, render_views
from nsplat.scene import ATTRIBUTES, SurfelScene
from nsplat.shading import lambert
from nsplat.view_model import cameras_of, surfel_view


def point_contributions(scene: SurfelScene, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                        cfg: RenderConfig, *, seed: int = 0, chunk: int = 12,
                        measure: Literal["radiance", "weight"] = "radiance",
                        shading: Literal["lambert", "none", "sh"] = "lambert", part: tuple[int, int] = (0, 1)
                        ) -> torch.Tensor:
    """Per-point visual contribution summed over views: ``[N]`` (no gradient).

    ``measure="weight"``: ``Σ_views Σ_x w_k(x)`` (total compositing weight). ``measure="radiance"``:
    ``Σ_views Σ_x w_k(x) · ‖c_k‖`` with ``c_k`` the point's (shaded, per camera) colour, so a visible but
    black point — e.g. an outlier that learned to vanish against the black background — counts as
    contributing nothing. Computed as the gradient of the summed one-channel image w.r.t. a unit probe
    (``∂I(x)/∂f_k = w_k(x)``); with the sampled op it is the Horvitz–Thompson estimate (estimator
    ``ht``), zero exactly for points never sampled with non-zero weight.

    ``part=(r, P)`` renders only every ``P``-th block of views starting at block ``r`` (a block is one
    camera, or ``chunk`` cameras without per-camera shading), with the same seeds as the whole: the ``P``
    parts sum to the whole.
    """
    with torch.no_grad():
        geo = (scene.means.detach(), scene.normals.detach(), scene.scales.detach(), scene.opacities.detach())
        feats = scene.features.detach()
    N, dtype, device = scene.num_points, geo[0].dtype, geo[0].device
    total = torch.zeros(N, dtype=dtype, device=device)
    per_camera = measure == "radiance" and shading == "lambert"
    step = 1 if per_camera else chunk
    for s in range(part[0] * step, viewmats.shape[0], part[1] * step):
        vm, K = viewmats[s:s + step], Ks[s:s + step]
        if measure == "weight":
            colour = torch.ones(N, dtype=dtype, device=device)
        elif per_camera:
            colour = lambert(feats, geo[1], vm)[0].norm(dim=-1)
        else:  # unshaded; view-dependent colour ("sh"): its mean colour, the first three channels
            colour = (feats[:, :3] if shading == "sh" else feats).norm(dim=-1)
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


@torch.no_grad()
def cap_scales(scene: SurfelScene, max_scale: float) -> None:
    """Clamp every per-point tangent std-dev of ``scene`` to at most ``max_scale`` (world units) in place;
    ``0``: nothing happens."""
    if max_scale > 0:
        scene.tensor("scales").clamp_(max=math.log(max_scale))


@torch.no_grad()
def reset_opacities(scene: SurfelScene, value: float, optimizer: torch.optim.Optimizer) -> int:
    """Lower every per-point opacity of ``scene`` above ``value`` to ``value`` in place (the opacity reset of
    3DGS: surfels must earn their opacity again, and those that only fake other views' content fade) and zero
    the opacity logits' Adam moments. Returns the number of surfels lowered."""
    logits = scene.tensor("opacities")
    cap = math.log(value / (1.0 - value))
    lowered = int((logits > cap).sum())
    logits.clamp_(max=cap)
    reset_rows([optimizer], [logits], torch.arange(logits.shape[0], device=logits.device))
    return lowered


#: The paper's learning rate for every attribute (attributes a scene keeps frozen are ignored).
PAPER_LR = {"means": 0.01, "normals": 0.01, "scales": 0.01, "opacities": 0.01, "features": 0.01}


@dataclasses.dataclass
class FitConfig:
    """Optimisation settings (defaults: the paper's).

    Attributes:
        epochs: passes over all views (the schedule's length; the engine counts steps,
            ``epochs × ceil(views / batch)``). batch: views per step.
        learn: Adam learning rate per attribute (``means``, ``normals``, ``scales``, ``opacities``,
            ``features``); which attributes are learnable is the scene's ``learn`` list.
        lr_decays: number of times the rate is multiplied by ``lr_gamma``, at regular epoch intervals.
        anneal_epochs: the last this many epochs also decay the rate geometrically, one factor per epoch, so
            that the last epoch runs at ``anneal_factor`` times the step schedule's rate (on top of the
            ``lr_decays`` halvings, which stay where they are). Single-view steps leave the surfels jittering
            at the scale of the rate; the tail lets them settle. 0 (default): no tail.
        betas: Adam decay rates.
        shading: ``lambert`` (features are albedo, shaded per camera), ``none`` (features rendered as is) or
            ``sh`` (features are view-dependent RGB, spherical harmonics: :func:`nsplat.sh.view_colour`).
        reposition: move non-contributing points after every ``reposition_every``-th epoch (paper: every
            epoch; each check renders all views once more, so CPU runs may space it out).
            contribution: what "contributes" means (:func:`point_contributions`): ``radiance`` (weight ×
            colour, the paper's "visual contribution", default) or ``weight``. min_weight: a point contributes when
            its contribution summed over all views is at least this. jitter: tangent offset of a moved
            point, in units of its source point's scale.
        densify: adaptive density control (:class:`nsplat.densify.DensifyConfig`; off by default).
        ssim_weight: share ``s`` in [0, 1] of D-SSIM in the image loss ``(1 − s)·L1 + s·D-SSIM`` (3DGS uses
            0.2); 0 (default): L1 alone.
        sh_rest_lr: with ``shading: sh``, the SH coefficients beyond the mean colour (feature channels
            ``3:``) step at this fraction (in (0, 1]) of the features' rate (3DGS: 1/20); 1 (default): the same.
        coarse_epochs: the first this many epochs fit the views at ``1/coarse_factor`` of their resolution
            (:meth:`~nsplat.data.views.PosedViews.downscaled`: block means, scaled intrinsics; the low-pass
            stays in pixels of the image rendered), a coarse-to-fine schedule that makes early steps cheaper;
            repositioning and validation use the full resolution. 0 (default): off.
        max_scale: cap on every tangent std-dev (world units), enforced after each step by clamping the
            log-scales (a projection; Adam's moments are left as they are). A few surfels that grow far beyond
            their neighbours slow every render: their untruncated tails turn empty background pixels into
            pixels the sampler must fill with m samples (docs/op.md §5; docs/results.md "Time to quality",
            session 6); needs per-point scales. 0 (default): no cap.
        opacity_resets: epochs (counted from 1) after which every opacity above ``reset_opacity`` is lowered to it
            and the opacity moments are zeroed (:func:`reset_opacities`); needs learned per-point opacities.
            Empty (default): never.
        mask_weight: weight of a coverage term ``mask_weight · mean |alpha − mask|`` added to the L1 image
            loss, against the views' masks (the alpha of RGBA images): silhouettes are fitted directly, not
            only through the colour contrast with the background. 0 (default): off; > 0 needs masks.
    """

    epochs: int = 300
    batch: int = 12
    learn: dict[str, float] = dataclasses.field(default_factory=lambda: dict(PAPER_LR))
    lr_decays: int = 5
    lr_gamma: float = 0.5
    anneal_epochs: int = 0
    anneal_factor: float = 1.0
    betas: tuple[float, float] = (0.9, 0.999)
    shading: Literal["lambert", "none", "sh"] = "lambert"
    reposition: bool = True
    reposition_every: int = 1
    contribution: Literal["radiance", "weight"] = "radiance"
    min_weight: float = 0.02
    jitter: float = 1.0
    densify: DensifyConfig = dataclasses.field(default_factory=DensifyConfig)
    mask_weight: float = 0.0
    ssim_weight: float = 0.0
    sh_rest_lr: float = 1.0
    coarse_epochs: int = 0
    coarse_factor: int = 2
    max_scale: float = 0.0
    opacity_resets: list[int] = dataclasses.field(default_factory=list)
    reset_opacity: float = 0.01

    def milestones(self) -> list[int]:
        """Epochs at which the rate is decayed: ``round(k·epochs/(lr_decays+1))``, k = 1..lr_decays."""
        return [round(k * self.epochs / (self.lr_decays + 1)) for k in range(1, self.lr_decays + 1)]

    def rate_factor(self, epoch: int) -> float:
        """Factor on every base rate during epoch ``epoch`` (0-based): ``lr_gamma`` per milestone passed, times
        ``anneal_factor^(j / anneal_epochs)`` in the ``j``-th epoch of the tail (j = 1..anneal_epochs)."""
        factor = self.lr_gamma ** sum(epoch >= m for m in self.milestones())
        j = epoch - (self.epochs - self.anneal_epochs) + 1
        if self.anneal_epochs > 0 and j > 0:
            factor *= self.anneal_factor ** (min(j, self.anneal_epochs) / self.anneal_epochs)
        return factor

    def __post_init__(self) -> None:
        require_fields(self, epochs=">=0", batch=">=1", lr_decays=">=0", lr_gamma=">0",
                       reposition_every=">=1", min_weight=">=0", jitter=">=0", mask_weight=">=0", ssim_weight="unit",
                       sh_rest_lr="prob", coarse_epochs=">=0", coarse_factor=">=1",
                       max_scale=">=0", anneal_epochs=">=0", anneal_factor="prob")
        require(0 < self.reset_opacity < 1, "reset_opacity", "a value in (0, 1)", self.reset_opacity)
        require(all(0 < e < self.epochs for e in self.opacity_resets), "opacity_resets",
                f"epochs in 1..{self.epochs - 1} (a reset after the last epoch would only lower the result)",
                self.opacity_resets)
        # epochs = 0 (no fit: e.g. stage 2 from a fitted geometry.ply) leaves the tail nothing to anneal
        require(self.epochs == 0 or self.anneal_epochs <= self.epochs, "anneal_epochs",
                f"at most epochs ({self.epochs})", self.anneal_epochs)
        require(all(k in ATTRIBUTES and v > 0 for k, v in self.learn.items()), "learn",
                f"positive rates for attributes among {list(ATTRIBUTES)}", self.learn)


def build(scene: SurfelScene, cfg: FitConfig, seed: int = 0) -> Trainables:
    """Module ``scene`` (and ``density``, the :class:`~nsplat.densify.DensityStats`, when densification is
    on), Adam ``fit`` over its learnable attributes, the epoch scheduler and the generator of the
    repositioning and densification draws."""
    if cfg.densify.enabled and "means" not in scene.cfg.learn:
        raise ValueError("densify.enabled: needs learnable means (the growth criterion is their gradient)")
    optimizer = torch.optim.Adam(scene.param_groups(cfg.learn), betas=tuple(cfg.betas))
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda epoch: cfg.rate_factor(epoch))
    modules: dict[str, torch.nn.Module] = {"scene": scene}
    if cfg.densify.enabled:
        modules["density"] = DensityStats(scene.num_points, scene.means.dtype, scene.means.device)
    return Trainables(modules=modules, optimizers={"fit": optimizer}, schedulers={"fit": scheduler},
                      generator=torch.Generator().manual_seed(seed))


def fit(scene: SurfelScene, views: PosedViews, cfg: FitConfig, render_cfg: RenderConfig, run_dir: str | Path, *,
        log: LogConfig | None = None, seed: int = 0, resume: bool = False, background: torch.Tensor | None = None,
        validate: Hook | None = None, desc: str = "fit") -> dict[str, float]:
    """Optimise ``scene`` in place so its renders match ``views`` (L1, per-view backward) on the engine.

    Args:
        scene: the surfels; its learnable attributes are optimised.
        views: target images ``[V,H,W,C]`` with their cameras.
        cfg: optimisation settings. render_cfg: the gateway's settings. log: the engine's cadences (steps).
        run_dir: TensorBoard logs go to ``run_dir/tb``, checkpoints to ``run_dir/checkpoints``.
        seed: run seed (op seeds: :func:`nsplat.engine.op_seed` streams ``fit``, ``reposition``, ``batches``).
        resume: continue from the last checkpoint in ``run_dir`` (bit-exact on the same machine).
        validate: the engine's validation hook ``f(step, writer) -> scalars`` (e.g. shape metrics).

    Returns:
        the last step's scalars.
    """
    V, W, H = len(views), views.width, views.height
    images, viewmats, Ks = views.images, views.viewmats, views.Ks
    masks = views.masks
    if cfg.mask_weight > 0 and masks is None:
        raise ConfigError("mask_weight: > 0 needs views with masks (RGBA images); these views have none")
    if cfg.max_scale > 0 and scene.cfg.scale is not None:
        raise ConfigError(f"max_scale: needs per-point scales (scene.scale: null); this scene's std-dev is the "
                          f"constant {scene.cfg.scale}")
    if cfg.opacity_resets and "opacities" not in scene.cfg.learn:
        raise ConfigError("opacity_resets: needs learned per-point opacities (scene.opacity: null and 'opacities' "
                          "in the learned attributes)")
    try:
        coarse = views.downscaled(cfg.coarse_factor) if cfg.coarse_epochs > 0 else views
    except ValueError as exc:
        raise ConfigError(f"coarse_factor: {exc}") from exc
    payload = latest_payload(Path(run_dir), resume)
    if payload is not None:  # a checkpoint of an earlier version holds a MultiStepLR state: the same rates
        payload["schedulers"]["fit"].setdefault("lr_lambdas", [None])
    rows = checkpoint_rows(payload, "scene", "_means")
    if rows is not None and rows != scene.num_points:  # densified before the checkpoint
        scene.resize_(rows)
    t = build(scene, cfg, seed)
    optimizer, scheduler = t.optimizers["fit"], t.schedulers["fit"]
    stats = t.modules.get("density")
    steps_per_epoch = math.ceil(V / cfg.batch)
    engine = Engine(Path(run_dir), log or LogConfig(), cfg.epochs * steps_per_epoch, desc=desc)
    start = engine.resume(t, payload)
    cap_scales(scene, cfg.max_scale)

    def step(k: int) -> dict[str, float]:
        epoch, s = divmod(k, steps_per_epoch)
        src = coarse if epoch < cfg.coarse_epochs else views  # the coarse-to-fine schedule
        w, h = src.width, src.height
        perm = torch.randperm(V, generator=generator(seed, "batches", epoch))
        idx = perm[s * cfg.batch:(s + 1) * cfg.batch]
        optimizer.zero_grad(set_to_none=True)
        loss_val = 0.0
        local = None if stats is None else DensityStats(scene.num_points, stats.grad.dtype, stats.grad.device)
        # Backward per view: memory stays at one view's graph; gradients are summed (over ranks too,
        # each rank rendering its share of the batch's slots j; a view's seed is its global slot's).
        for j in distributed.shard(idx.numel()):
            v = int(idx[j])
            img, alpha = render_views(scene, viewmats[v:v + 1], src.Ks[v:v + 1], w, h, render_cfg,
                                      seed=op_seed(seed, "fit", k * cfg.batch + j), shading=cfg.shading,
                                      background=background, with_alpha=True)
            target = src.images[v:v + 1]
            loss = (img - target).abs().mean()
            if cfg.ssim_weight > 0:
                dssim = dssim_loss(img.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2))
                loss = (1.0 - cfg.ssim_weight) * loss + cfg.ssim_weight * dssim
            if cfg.mask_weight > 0:
                loss = loss + cfg.mask_weight * (alpha[..., 0] - src.masks[v:v + 1].float()).abs().mean()
            loss = loss / idx.numel()
            means = scene.tensor("means")
            before = None if local is None or means.grad is None else means.grad.clone()
            loss.backward()
            loss_val += loss.item()
            if local is not None:  # this view's gradient of its own (pixel-mean) loss
                g = means.grad if before is None else means.grad - before
                local.observe(g * idx.numel(), means.detach(), viewmats[v], src.Ks[v], w * h)
        distributed.all_reduce_grads(optimizer)
        if stats is not None:  # every rank holds the whole batch's statistics (and checkpoints them)
            stats.add_(distributed.all_reduce_sum(local.grad), distributed.all_reduce_sum(local.views))
        rest = None
        if cfg.shading == "sh" and cfg.sh_rest_lr < 1.0 and "features" in scene.cfg.learn:
            rest = scene.tensor("features")[:, 3:].detach().clone()
        optimizer.step()
        if rest is not None:  # old + sh_rest_lr · (Adam's step): the higher bands move at the smaller rate
            with torch.no_grad():
                scene.tensor("features")[:, 3:].lerp_(rest, 1.0 - cfg.sh_rest_lr)
        cap_scales(scene, cfg.max_scale)
        out = distributed.all_reduce_scalars({"train/loss": loss_val})
        if s + 1 == steps_per_epoch:
            moved = 0
            if cfg.reposition and (epoch + 1) % cfg.reposition_every == 0:
                contrib = point_contributions(scene, viewmats, Ks, W, H, render_cfg,
                                              seed=op_seed(seed, "reposition", epoch), chunk=cfg.batch,
                                              measure=cfg.contribution, shading=cfg.shading,
                                              part=(distributed.rank(), distributed.world_size()))
                contrib = distributed.all_reduce_sum(contrib)
                moved = reposition(scene, contrib, cfg.min_weight, cfg.jitter, t.generator, optimizer)
            if stats is not None and cfg.densify.due(epoch + 1):
                counts = densify(scene, stats, cfg.densify, t.generator, [optimizer])
                out.update({f"densify/{k}": v for k, v in counts.items()})
            if epoch + 1 in cfg.opacity_resets:
                out["epoch/opacity_reset"] = float(reset_opacities(scene, cfg.reset_opacity, optimizer))
            scheduler.step()
            out.update({"epoch/moved": float(moved), "epoch/lr": optimizer.param_groups[0]["lr"]})
        return out

    cams = cameras_of(images, viewmats, Ks)
    return engine.train(t, step, start=start, validate=validate,
                        view=lambda: surfel_view(scene, cams, shading=cfg.shading, background=background,
                                                 render_cfg=render_cfg, task=desc, seed=op_seed(seed, "eval")))
