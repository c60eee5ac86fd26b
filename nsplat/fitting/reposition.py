"""Repositioning (paper §4): points that contribute nothing to any view move next to visible ones.

After every ``every``-th epoch but the last, the fitter renders every training view once more with a unit probe on each
point's colour (:func:`point_contributions`); points whose summed contribution stays below ``min_weight``
are moved next to a random contributing point (:func:`reposition`). Under torchrun each rank renders its
share of the views and the contributions are summed, so every rank moves the same points.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import torch

from nsplat.config import require, require_fields
from nsplat.fitting.strategy import FitState, Strategy
from nsplat.ops import tangent_frame
from nsplat.ops.tiled import point_weights_tiled
from nsplat.render.renderer import RenderConfig, render
from nsplat.render.shading import lambert
from nsplat.run import distributed
from nsplat.run.engine import op_seed
from nsplat.scene import SurfelScene


@dataclasses.dataclass
class RepositionConfig:
    """When and how non-contributing points move (``enabled: false``: never).

    Attributes:
        enabled: run the checks.
        every: check after every this many epochs (paper: 1; each check renders all views once more), except
            after the last epoch: a point moved then would keep its copied attributes unfitted.
        contribution: what "contributes" means (:func:`point_contributions`): ``radiance`` (weight × colour,
            the paper's "visual contribution") or ``weight``.
        exact: count the contributions with the exact compositing weights of every point in reach
            (:func:`nsplat.ops.tiled.point_weights_tiled`, no sampling) instead of the sampled op's estimate. A
            sample composites only the points it drew, so a point hidden behind a surface can show through it and
            count as contributing; with exact weights it counts as hidden and moves to the surface.
        min_weight: a point contributes when its contribution summed over all views is at least this and at
            least ``relative`` × the median contribution.
        relative: the relative part of that threshold (0: absolute only). With untruncated kernels a point hidden
            just behind the surface still contributes a little, never nothing; a relative threshold moves it too.
        jitter: tangent offset of a moved point, in units of its source point's std-dev.
    """

    enabled: bool = True
    every: int = 1
    contribution: Literal["radiance", "weight"] = "radiance"
    exact: bool = False
    min_weight: float = 0.02
    relative: float = 0.0
    jitter: float = 1.0

    def __post_init__(self) -> None:
        require_fields(self, every=">=1", min_weight=">=0", jitter=">=0")
        require(0 <= self.relative < 1, "relative", "a value in [0, 1)", self.relative)


def point_contributions(scene: SurfelScene, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                        cfg: RenderConfig, *, seed: int = 0, chunk: int = 12,
                        measure: Literal["radiance", "weight"] = "radiance",
                        shading: Literal["lambert", "none", "sh"] = "lambert", part: tuple[int, int] = (0, 1),
                        exact: bool = False) -> torch.Tensor:
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

    ``exact``: the weights are the exact ones of :func:`nsplat.ops.tiled.point_weights_tiled` (every point in reach,
    in depth order, no sampling; ``seed`` unused), ``chunk`` cameras a call.
    """
    with torch.no_grad():
        geo = (scene.means.detach(), scene.normals.detach(), scene.scales.detach(), scene.opacities.detach())
        feats = scene.features.detach()
    N, dtype, device = scene.num_points, geo[0].dtype, geo[0].device
    total = torch.zeros(N, dtype=dtype, device=device)
    per_camera = measure == "radiance" and shading == "lambert"
    if exact:
        for s in range(part[0] * chunk, viewmats.shape[0], part[1] * chunk):
            vm, K = viewmats[s:s + chunk], Ks[s:s + chunk]
            weights = point_weights_tiled(*geo, vm, K, width, height, near=cfg.near, far=cfg.far, lowpass=cfg.lowpass,
                                          backface_cull=cfg.backface_cull)             # [b,N]
            if measure == "weight":
                total += weights.sum(0)
            elif per_camera:
                total += (weights * lambert(feats, geo[1], vm).norm(dim=-1)).sum(0)
            else:
                total += weights.sum(0) * (feats[:, :3] if shading == "sh" else feats).norm(dim=-1)
        return total
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
    """Move every point with ``contributions [N] < min_weight`` next to a random visible point.

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


class Reposition(Strategy):
    """The repositioning checks as a fitter strategy (logs ``epoch/moved`` after every check)."""

    def __init__(self, cfg: RepositionConfig) -> None:
        self.cfg = cfg

    def after_step(self, fit: FitState, step: int) -> dict[str, float]:
        epochs = fit.epoch_done(step)
        if epochs is None or epochs % self.cfg.every or epochs == fit.epochs:
            return {}
        v = fit.views
        contrib = point_contributions(fit.scene, v.viewmats, v.Ks, v.width, v.height, fit.render_cfg,
                                      seed=op_seed(fit.seed, "reposition", epochs - 1), chunk=fit.batch,
                                      measure=self.cfg.contribution, shading=fit.shading,
                                      part=(distributed.rank(), distributed.world_size()), exact=self.cfg.exact)
        contrib = distributed.all_reduce_sum(contrib)
        threshold = max(self.cfg.min_weight, self.cfg.relative * float(contrib.median()))
        moved = reposition(fit.scene, contrib, threshold, self.cfg.jitter, fit.generator, fit.optimizer)
        return {"epoch/moved": float(moved)}
