"""Adaptive density control, a fitter strategy: split, clone and prune on a schedule.

The fitter (:func:`nsplat.fitting.fit`) renders a step's views in one op call and keeps each camera's projected
screen means ``μ₂d [B,N,2]`` in the graph (:attr:`Strategy.screen_grads`); after the backward
:meth:`DensityStats.observe` takes each view's own screen-space gradient magnitude ``‖∂L_v/∂μ₂d‖`` (loss per pixel
of motion, times the view's pixel count) and accumulates it per point. Every ``every`` epochs, :func:`densify` acts
on the averages:

* **grow** where the average screen-space gradient exceeds ``grad_threshold`` (the image wants the point
  elsewhere or wants more points there): surfels larger than ``split_size`` (world std-dev) are
  **split** into ``children`` surfels drawn from their own kernel, each ``shrink`` times smaller;
  smaller ones are **cloned** (the copy is offset by ``clone_jitter`` of its std-dev in the tangent
  plane, so the two separate under the next gradients);
* **prune** surfels whose opacity fell below ``prune_opacity``, whose std-dev exceeds ``prune_scale``, or
  (``prune_weight``) whose compositing weight summed over every training view stays below ``prune_weight``
  pixels: surfels that contribute nothing from any training view. That sum is measured at the event by one
  more render of every view (:func:`nsplat.fitting.reposition.point_contributions`, ``measure="weight"``).

The point set is rebuilt with :meth:`nsplat.scene.SurfelScene.gather_` (optimiser state gathered; new
rows start without momentum, as in 3DGS). Growth per event is capped by ``max_growth`` and the total by
``max_points``, highest gradients first. Under torchrun the statistics (and the contributions) are summed over
ranks, so every rank takes the same decisions.

During a fit the point set changes only between steps: the learning-rate schedule, the SH bands' smaller
rate and the scale cap apply to the new rows as to the old ones from the next step on.
"""
from __future__ import annotations

import dataclasses
from typing import Iterable

import torch
from torch import nn

from nsplat.config import ConfigError, require_fields
from nsplat.data.views import PosedViews
from nsplat.fitting.reposition import point_contributions
from nsplat.fitting.strategy import FitState, Strategy, ViewRender
from nsplat.ops import tangent_frame
from nsplat.run import distributed
from nsplat.run.engine import op_seed
from nsplat.scene import SurfelScene


@dataclasses.dataclass
class DensifyConfig:
    """When and how the fitter changes its point set (``enabled: false``: never; nothing allocated).

    Attributes:
        enabled: run density control.
        start: first event after this many epochs. every: epochs between events.
        stop: no event after this many epochs (``0``: until the last epoch's start).
        grad_threshold: average screen-space positional gradient (loss per pixel of motion, with the
            per-view loss a mean over pixels and channels, multiplied by the pixel count) above which
            a point grows.
        split_size: world std-dev above which a growing point is split (else cloned).
        children: surfels a split point becomes. shrink: their std-dev divisor.
        clone_jitter: tangent offset of a clone, in units of its std-dev.
        max_growth: at most this fraction of the current points grows per event.
        max_points: never exceed this many points.
        prune_opacity: prune below this opacity (only with per-point opacities; ``0``: never).
        prune_scale: prune points whose largest std-dev exceeds this (world units; ``0``: never).
        prune_weight: prune points whose compositing weight summed over all training views (pixels) is
            below this at an event (``0``: never; costs one render of every view per event).
    """

    enabled: bool = False
    start: int = 1
    every: int = 1
    stop: int = 0
    grad_threshold: float = 0.05
    split_size: float = 0.02
    children: int = 2
    shrink: float = 1.6
    clone_jitter: float = 0.5
    max_growth: float = 0.5
    max_points: int = 50000
    prune_opacity: float = 0.02
    prune_scale: float = 0.0
    prune_weight: float = 0.0

    def __post_init__(self) -> None:
        require_fields(self, start=">=1", every=">=1", stop=">=0", grad_threshold=">=0", split_size=">=0",
                       children=">=1", shrink=">0", clone_jitter=">=0", max_growth=">=0", max_points=">=1",
                       prune_opacity=">=0", prune_scale=">=0", prune_weight=">=0")

    def due(self, epochs_done: int) -> bool:
        """Whether an event runs after ``epochs_done`` epochs."""
        if not self.enabled or epochs_done < self.start or (self.stop and epochs_done > self.stop):
            return False
        return (epochs_done - self.start) % self.every == 0


class DensityStats(nn.Module):
    """Per-point accumulators between two events (checkpointed with the fitter's state).

    Buffers: ``grad [N]`` sum of screen-space gradient magnitudes, ``views [N]`` number of views that
    gave the point a non-zero gradient.
    """

    def __init__(self, num_points: int, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        super().__init__()
        self.register_buffer("grad", torch.zeros(num_points, dtype=dtype, device=device))
        self.register_buffer("views", torch.zeros(num_points, dtype=dtype, device=device))

    def resize_(self, num_points: int) -> None:
        """Zeroed accumulators for ``num_points`` points."""
        self.grad = self.grad.new_zeros(num_points)
        self.views = self.views.new_zeros(num_points)

    @torch.no_grad()
    def observe(self, grad_means2d: torch.Tensor, pixels: int) -> None:
        """Accumulate views: ``grad_means2d [b,N,2]`` = each view's own ∂L_v/∂μ₂d (its loss a mean over pixels,
        ``μ₂d`` in pixels); ``pixels``: the loss's pixel count."""
        g_px = grad_means2d.norm(dim=-1) * pixels
        seen = g_px > 0
        self.grad += torch.where(seen, g_px, torch.zeros_like(g_px)).sum(0)
        self.views += seen.to(self.views.dtype).sum(0)

    @torch.no_grad()
    def add_(self, grad: torch.Tensor, views: torch.Tensor) -> None:
        """Add accumulated ``grad [N]`` and ``views [N]`` (e.g. one step's, summed over ranks)."""
        self.grad += grad
        self.views += views

    def average(self) -> torch.Tensor:
        """``[N]`` mean screen-space gradient over the views that saw each point (0 when none)."""
        return self.grad / self.views.clamp_min(1)


@torch.no_grad()
def densify(scene: SurfelScene, stats: DensityStats, cfg: DensifyConfig, generator: torch.Generator,
            optimizers: Iterable[torch.optim.Optimizer] = (), contributions: torch.Tensor | None = None
            ) -> dict[str, float]:
    """One density-control event (module docstring); resets ``stats``. ``contributions [N]``: each point's
    compositing weight summed over the training views (:func:`point_contributions`), needed when
    ``cfg.prune_weight > 0``. Returns counts ``{split, cloned, pruned, points}``."""
    N = scene.num_points
    device = scene.means.device
    grad = stats.average()
    scales = scene.scales
    size = scales.max(dim=-1).values
    prune = torch.zeros(N, dtype=torch.bool, device=device)
    if cfg.prune_opacity > 0 and scene.cfg.opacity is None:
        prune |= scene.opacities < cfg.prune_opacity
    if cfg.prune_scale > 0:
        prune |= size > cfg.prune_scale
    if cfg.prune_weight > 0:
        if contributions is None or contributions.shape != (N,):
            raise ValueError(f"densify: prune_weight needs the contributions [{N}], got "
                             f"{None if contributions is None else list(contributions.shape)}")
        prune |= contributions < cfg.prune_weight
    # Candidates by decreasing gradient; a split adds children - 1 rows, a clone 1. Keep the longest
    # prefix within the event's budget of new rows (max_growth) and the total cap (max_points).
    cand = ((grad > cfg.grad_threshold) & ~prune).nonzero().squeeze(1)
    cand = cand[torch.argsort(grad[cand], descending=True, stable=True)]
    added = torch.where(size[cand] > cfg.split_size, cfg.children - 1, 1)
    budget = min(int(cfg.max_growth * N), cfg.max_points - (N - int(prune.sum())))
    cand = cand[torch.cumsum(added, 0) <= budget]
    split = torch.zeros(N, dtype=torch.bool, device=device)
    split[cand] = size[cand] > cfg.split_size
    clone = torch.zeros(N, dtype=torch.bool, device=device)
    clone[cand] = ~split[cand]
    # Children of a split point replace it; a clone is added beside its original.
    split_idx, clone_idx = split.nonzero().squeeze(1), clone.nonzero().squeeze(1)
    stay_idx = (~prune & ~split).nonzero().squeeze(1)
    child_idx = split_idx.repeat_interleave(cfg.children)
    index = torch.cat([stay_idx, clone_idx, child_idx])
    fresh = torch.zeros(index.numel(), dtype=torch.bool, device=device)
    fresh[stay_idx.numel():] = True
    scene.gather_(index, optimizers, fresh)

    new_rows = torch.arange(stay_idx.numel(), index.numel(), device=device)
    if new_rows.numel():
        normals = scene.normals[new_rows]
        sc = scene.scales[new_rows]
        t0, t1 = tangent_frame(normals)
        is_child = torch.zeros(new_rows.numel(), dtype=torch.bool, device=device)
        is_child[clone_idx.numel():] = True
        spread = torch.where(is_child, torch.ones_like(is_child, dtype=sc.dtype),
                             torch.full_like(is_child, cfg.clone_jitter, dtype=sc.dtype))
        z = torch.randn(new_rows.numel(), 2, generator=generator).to(sc) * sc * spread[:, None]
        values = {"means": scene.means[new_rows] + z[:, :1] * t0 + z[:, 1:] * t1}
        if scene.cfg.scale is None:
            values["scales"] = torch.where(is_child[:, None], sc / cfg.shrink, sc)
        scene.set_values(values, new_rows)
    stats.resize_(scene.num_points)
    return {"split": float(split_idx.numel()), "cloned": float(clone_idx.numel()),
            "pruned": float(prune.sum()), "points": float(scene.num_points)}


class Densify(Strategy):
    """Density control as a fitter strategy: per-view statistics after each backward, summed over the step's
    views (and ranks) after Adam's step, and an event after every due epoch (logs ``densify/<count>``; with
    ``prune_weight``, the contributions are rendered first with the op seeds of stream ``densify``)."""

    screen_grads = True  # the statistics are of each view's own screen-space gradient (kept apart per camera)

    def __init__(self, cfg: DensifyConfig) -> None:
        self.cfg = cfg
        self.stats: DensityStats | None = None
        self._step: DensityStats | None = None        # this step's views (this rank's share)

    def attach(self, scene: SurfelScene, views: PosedViews | None) -> dict[str, nn.Module]:
        if "means" not in scene.cfg.learn:
            raise ConfigError("densify.enabled: needs learnable means (the growth criterion is their gradient)")
        self.stats = DensityStats(scene.num_points, scene.means.dtype, scene.means.device)
        return {"density": self.stats}

    def after_backward(self, fit: FitState, view: ViewRender) -> None:
        if self._step is None:
            self._step = DensityStats(fit.scene.num_points, self.stats.grad.dtype, self.stats.grad.device)
        for m2d in view.means2d:
            if m2d.grad is not None:  # None: no point of these views received a gradient
                self._step.observe(m2d.grad.to(self._step.grad.dtype) * view.share, fit.views.width * fit.views.height)

    def after_step(self, fit: FitState, step: int) -> dict[str, float]:
        local = self._step if self._step is not None else DensityStats(fit.scene.num_points, self.stats.grad.dtype,
                                                                          self.stats.grad.device)
        self.stats.add_(distributed.all_reduce_sum(local.grad), distributed.all_reduce_sum(local.views))
        self._step = None
        epochs = fit.epoch_done(step)
        if epochs is None or not self.cfg.due(epochs):
            return {}
        contrib = None
        if self.cfg.prune_weight > 0:
            v = fit.views
            contrib = point_contributions(fit.scene, v.viewmats, v.Ks, v.width, v.height, fit.render_cfg,
                                          seed=op_seed(fit.seed, "densify", epochs - 1), chunk=fit.batch,
                                          measure="weight", part=(distributed.rank(), distributed.world_size()))
            contrib = distributed.all_reduce_sum(contrib)
        counts = densify(fit.scene, self.stats, self.cfg, fit.generator, [fit.optimizer], contrib)
        return {f"densify/{k}": v for k, v in counts.items()}
