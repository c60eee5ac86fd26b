"""The surfel fitter: a :class:`~nsplat.scene.SurfelScene` fitted to posed images (paper §4).

Used by the shape task (:mod:`nsplat.tasks.reconstruct`) and by stage 1 of the neural task. Each step renders
the step's views in one op call through the gateway (:mod:`nsplat.render.renderer`; one call per view only for a
strategy
with ``per_view``), takes the L1 distance to their images and backpropagates; Adam steps once per step, the rate
follows :meth:`FitConfig.rate_factor` per epoch. What is optional (repositioning, density control, a mask
term) plugs in as a :class:`~nsplat.fitting.strategy.Strategy`. The engine (:mod:`nsplat.run.engine`) runs the
steps: logging, atomic checkpoints, exact resume (also across changes of the point count). Data-parallel
under torchrun (:mod:`nsplat.run.distributed`): each rank renders its share of a step's views and gradients are
summed over ranks.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Literal

import torch

from nsplat.config import ConfigError, require, require_fields
from nsplat.data.views import PosedViews
from nsplat.fitting.densify import Densify, DensifyConfig
from nsplat.fitting.mask_loss import MaskLoss, MaskLossConfig
from nsplat.fitting.reposition import Reposition, RepositionConfig
from nsplat.fitting.strategy import FitState, Strategy, ViewRender
from nsplat.render.renderer import RenderConfig, render_views
from nsplat.render.view_model import cameras_of, surfel_view
from nsplat.run import distributed
from nsplat.run.engine import Engine, Hook, LogConfig, Trainables, checkpoint_rows, generator, latest_payload, op_seed
from nsplat.scene import ATTRIBUTES, SurfelScene

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
        lr_gamma: the factor of each of those decays.
        anneal_epochs: the last this many epochs also decay the rate geometrically, one factor per epoch, so
            that the last epoch runs at ``anneal_factor`` times the step schedule's rate (on top of the
            ``lr_decays`` decays, which stay where they are). Single-view steps leave the surfels jittering
            at the scale of the rate; the tail lets them settle. 0: no tail.
        anneal_factor: the rate factor the tail ends at, in (0, 1].
        betas: Adam decay rates.
        shading: ``lambert`` (features are albedo, shaded per camera), ``none`` (features rendered as is) or
            ``sh`` (features are view-dependent RGB, spherical harmonics: :func:`nsplat.render.sh.view_colour`).
        sh_rest_lr: with ``shading: sh``, the SH coefficients beyond the mean colour (feature channels
            ``3:``) step at this fraction (in (0, 1]) of the features' rate (3DGS: 1/20); 1: the same.
        max_scale: cap on every tangent std-dev (world units), enforced before the first render and after
            each step by clamping the log-scales (a projection; Adam's moments are left as they are). A few
            surfels that grow far beyond their neighbours slow every render: their untruncated tails turn
            empty background pixels into pixels the sampler must fill with m samples (docs/op.md §5); needs
            per-point scales. 0: no cap.
        reposition: :class:`~nsplat.fitting.reposition.RepositionConfig` (moves non-contributing points).
        densify: :class:`~nsplat.fitting.densify.DensifyConfig` (adaptive density control; off by default).
        mask_loss: :class:`~nsplat.fitting.mask_loss.MaskLossConfig` (a coverage term; off by default).
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
    sh_rest_lr: float = 1.0
    max_scale: float = 0.0
    reposition: RepositionConfig = dataclasses.field(default_factory=RepositionConfig)
    densify: DensifyConfig = dataclasses.field(default_factory=DensifyConfig)
    mask_loss: MaskLossConfig = dataclasses.field(default_factory=MaskLossConfig)

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

    def strategies(self) -> list[Strategy]:
        """The optional parts this config turns on, in the order the fitter runs them."""
        out: list[Strategy] = []
        if self.mask_loss.weight > 0:
            out.append(MaskLoss(self.mask_loss))
        if self.reposition.enabled:
            out.append(Reposition(self.reposition))
        if self.densify.enabled:
            out.append(Densify(self.densify))
        return out

    def __post_init__(self) -> None:
        require_fields(self, epochs=">=0", batch=">=1", lr_decays=">=0", lr_gamma=">0", sh_rest_lr="prob",
                       max_scale=">=0", anneal_epochs=">=0", anneal_factor="prob", betas="rate")
        # epochs = 0 (no fit: e.g. stage 2 from a fitted geometry.ply) leaves the tail nothing to anneal
        require(self.epochs == 0 or self.anneal_epochs <= self.epochs, "anneal_epochs",
                f"at most epochs ({self.epochs})", self.anneal_epochs)
        require(all(k in ATTRIBUTES and v > 0 for k, v in self.learn.items()), "learn",
                f"positive rates for attributes among {list(ATTRIBUTES)}", self.learn)


def build(scene: SurfelScene, cfg: FitConfig, seed: int = 0, strategies: list[Strategy] | None = None,
          views: PosedViews | None = None) -> Trainables:
    """Module ``scene`` (and the strategies' per-point state, e.g. ``density``), Adam ``fit`` (fused: one native loop
    over the parameters) over its
    learnable attributes, the epoch scheduler and the generator of the strategies' draws.

    ``strategies`` default to ``cfg.strategies()``; each checks that it applies to ``scene`` (and ``views``)."""
    modules: dict[str, torch.nn.Module] = {"scene": scene}
    for strategy in cfg.strategies() if strategies is None else strategies:
        modules.update(strategy.attach(scene, views))
    optimizer = torch.optim.Adam(scene.param_groups(cfg.learn), betas=tuple(cfg.betas), fused=True)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda epoch: cfg.rate_factor(epoch))
    return Trainables(modules=modules, optimizers={"fit": optimizer}, schedulers={"fit": scheduler},
                      generator=torch.Generator().manual_seed(seed))


@torch.no_grad()
def cap_scales(scene: SurfelScene, max_scale: float) -> None:
    """Clamp every per-point tangent std-dev of ``scene`` to at most ``max_scale`` (world units) in place;
    ``0``: nothing happens."""
    if max_scale > 0:
        scene.tensor("scales").clamp_(max=math.log(max_scale))


def adam_step(scene: SurfelScene, optimizer: torch.optim.Optimizer, cfg: FitConfig) -> None:
    """Adam's step, with the higher SH bands at ``cfg.sh_rest_lr`` of the rate, then the scale cap."""
    rest = None
    if cfg.shading == "sh" and cfg.sh_rest_lr < 1.0 and "features" in scene.cfg.learn:
        rest = scene.tensor("features")[:, 3:].detach().clone()
    optimizer.step()
    if rest is not None:  # old + sh_rest_lr · (Adam's step): the higher bands move at the smaller rate
        with torch.no_grad():
            scene.tensor("features")[:, 3:].lerp_(rest, 1.0 - cfg.sh_rest_lr)
    cap_scales(scene, cfg.max_scale)


def _checkpoint(scene: SurfelScene, run_dir: Path, resume: bool) -> dict | None:
    """The checkpoint payload to resume from (``None``: a fresh run); the scene is resized to its point count."""
    payload = latest_payload(run_dir, resume)
    if payload is not None:  # a checkpoint of an earlier version holds a MultiStepLR state: the same rates
        payload["schedulers"]["fit"].setdefault("lr_lambdas", [None])
    rows = checkpoint_rows(payload, "scene", "_means")
    if rows is not None and rows != scene.num_points:  # the point count changed before the checkpoint
        scene.resize_(rows)
    return payload


def _group_loss(state: FitState, strategies: list[Strategy], views_k: list[int], seeds: list[int], share: int,
                screen: bool, background: torch.Tensor | None) -> torch.Tensor:
    """Render the views ``views_k`` in one op call (``seeds``: one per view), add the strategies' loss terms,
    backpropagate the loss over ``share`` (the step's batch size) and run the strategies' ``after_backward``;
    returns the detached loss (0-dim)."""
    views, multi = state.views, len(views_k) > 1
    image, alpha, *means2d = render_views(
        state.scene, views.viewmats[views_k], views.Ks[views_k], views.width, views.height, state.render_cfg,
        seed=torch.tensor(seeds) if multi else seeds[0], shading=state.shading, background=background,
        with_alpha=True, with_means2d=screen)
    for m2d in means2d[0] if screen else []:  # the views' own screen-space gradients (Strategy.screen_grads)
        m2d.retain_grad()
    view = ViewRender(views_k, image, alpha, share, *means2d)
    loss = (image - views.images[views_k]).abs().mean(dim=(1, 2, 3)).sum()
    for strategy in strategies:
        term = strategy.loss(state, view)
        loss = loss if term is None else loss + term
    loss = loss / view.share
    loss.backward()
    for strategy in strategies:
        strategy.after_backward(state, view)
    return loss.detach()


def fit(scene: SurfelScene, views: PosedViews, cfg: FitConfig, render_cfg: RenderConfig, run_dir: str | Path, *,
        log: LogConfig | None = None, seed: int = 0, resume: bool = False, background: torch.Tensor | None = None,
        validate: Hook | None = None, desc: str = "fit") -> dict[str, float]:
    """Optimise ``scene`` in place so its renders match ``views`` (L1 of each view) on the engine.

    Args:
        scene: the surfels; its learnable attributes are optimised.
        views: target images ``[V,H,W,C]`` with their cameras.
        cfg: optimisation settings. render_cfg: the gateway's settings. log: the engine's cadences (steps).
        run_dir: TensorBoard logs go to ``run_dir/tb``, checkpoints to ``run_dir/checkpoints``.
        seed: run seed (op seeds: :func:`nsplat.run.engine.op_seed` streams ``fit``, ``reposition``, ``batches``).
        resume: continue from the last checkpoint in ``run_dir`` (bit-exact on the same machine).
        background: ``[C]`` colour under the splats (default: the render config's).
        validate: the engine's validation hook ``f(step, writer) -> scalars`` (e.g. shape metrics).

    Returns:
        the last step's scalars, with ``time/train_s`` and ``time/train_cpu_s``: the wall and CPU seconds of the
        steps over every segment of a resumed run (CPU time from step ``time/cpu_since``, see
        :meth:`nsplat.run.engine.Engine.train`).
    """
    if cfg.max_scale > 0 and scene.cfg.scale is not None:
        raise ConfigError(f"max_scale: needs per-point scales (scene.scale: null); this scene's std-dev is the "
                          f"constant {scene.cfg.scale}")
    payload = _checkpoint(scene, Path(run_dir), resume)
    strategies = cfg.strategies()
    t = build(scene, cfg, seed, strategies, views)
    optimizer, scheduler = t.optimizers["fit"], t.schedulers["fit"]
    state = FitState(scene, views, optimizer, t.generator, render_cfg, cfg.shading, seed,
                     steps_per_epoch=math.ceil(len(views) / cfg.batch), batch=cfg.batch, epochs=cfg.epochs)
    engine = Engine(Path(run_dir), log or LogConfig(), cfg.epochs * state.steps_per_epoch, desc=desc)
    start = engine.resume(t, payload)
    cap_scales(scene, cfg.max_scale)

    def step(k: int) -> dict[str, float | torch.Tensor]:
        epoch, s = divmod(k, state.steps_per_epoch)
        idx = torch.randperm(len(views), generator=generator(seed, "batches", epoch))[s * cfg.batch:(s + 1) * cfg.batch]
        optimizer.zero_grad(set_to_none=True)
        loss_sum = torch.zeros((), dtype=torch.float64, device=scene.means.device)  # on the device, logged lazily
        # The rank's share of the batch's slots j (a view's seed is its global slot's), rendered in one op call
        # with one seed per view (shaded views with per-camera features) when no strategy needs each view's own
        # gradient (the same samples and images as one call per view, op.md §3), else one call per view;
        # gradients are summed over the calls and over ranks.
        share = list(distributed.shard(idx.numel()))
        together, screen = not any(st.per_view for st in strategies), any(st.screen_grads for st in strategies)
        for group in ([share] if together and share else [[j] for j in share]):
            views_k = [int(idx[j]) for j in group]
            seeds = [op_seed(seed, "fit", k * cfg.batch + j) for j in group]
            loss_sum += _group_loss(state, strategies, views_k, seeds, idx.numel(), screen, background).double()
        distributed.all_reduce_grads(optimizer)
        adam_step(scene, optimizer, cfg)
        out = distributed.all_reduce_scalars({"train/loss": loss_sum})
        for strategy in strategies:
            out.update(strategy.after_step(state, k))
        if state.epoch_done(k) is not None:
            scheduler.step()
            out["epoch/lr"] = optimizer.param_groups[0]["lr"]
        return out

    cams = cameras_of(views.images, views.viewmats, views.Ks)
    scalars = engine.train(t, step, start=start, validate=validate,
                           view=lambda: surfel_view(scene, cams, shading=cfg.shading, background=background,
                                                    render_cfg=render_cfg, task=desc, seed=op_seed(seed, "eval")))
    return {**scalars, "time/train_s": float(t.extra.get("seconds", 0.0)),
            "time/train_cpu_s": float(t.extra.get("cpu_seconds", 0.0)), "time/cpu_since": int(t.extra["cpu_since"])}
