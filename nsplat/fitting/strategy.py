"""The fitter's plug-in interface: a :class:`Strategy` changes what a fit does around its steps.

The fitter (:func:`nsplat.fitting.fit`) is the algorithm alone: render the step's views, L1 against their
images, backward, Adam. Everything optional plugs in as a strategy (in the spirit of gsplat's ``Strategy``), each in
its own module with its own config section:

* :class:`nsplat.fitting.reposition.Reposition` — moves points that contribute nothing (paper §4);
* :class:`nsplat.fitting.densify.Densify` — adaptive density control (split, clone, prune);
* :class:`nsplat.fitting.mask_loss.MaskLoss` — a coverage term against the views' masks.

A strategy sees the running fit through :class:`FitState` and may change the point set; it does so through
:meth:`nsplat.scene.SurfelScene.replace` / :meth:`~nsplat.scene.SurfelScene.gather_`, which keep the
optimiser's per-row state consistent (:mod:`nsplat.points`). Its per-point accumulators are modules that the
engine checkpoints with the scene, so a resumed fit equals an uninterrupted one.
"""
from __future__ import annotations

import dataclasses

import torch
from torch import nn

from nsplat.data.views import PosedViews
from nsplat.render.renderer import RenderConfig
from nsplat.scene import SurfelScene


@dataclasses.dataclass
class FitState:
    """What a strategy sees of a running fit.

    Attributes:
        scene: the surfels being fitted (their point count may change between steps).
        views: the training views ``[V,H,W,C]`` with their cameras.
        optimizer: Adam over the scene's learnable attributes.
        generator: the fit's CPU generator for random draws (checkpointed: exact resume).
        render_cfg: the render settings of the fit. shading: how features become colour (``lambert``,
            ``none``, ``sh``). seed: the run seed (op seeds: :func:`nsplat.run.engine.op_seed`).
        steps_per_epoch: steps per pass over all views. batch: views per step. epochs: epochs of the fit.
    """

    scene: SurfelScene
    views: PosedViews
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    render_cfg: RenderConfig
    shading: str
    seed: int
    steps_per_epoch: int
    batch: int
    epochs: int

    def epoch_done(self, step: int) -> int | None:
        """The number of epochs completed by step ``step`` (0-based) when it is an epoch's last step, else
        ``None``."""
        epoch, s = divmod(step, self.steps_per_epoch)
        return epoch + 1 if s + 1 == self.steps_per_epoch else None


@dataclasses.dataclass
class ViewRender:
    """Training views rendered together (one op call) in a step.

    Attributes:
        indices: the views' indices in :attr:`FitState.views` (one unless every strategy accepts several).
        image: ``[b,H,W,C]`` renders. alpha: ``[b,H,W,1]`` coverage.
        share: views in the step (each view's loss is divided by it).
        means2d: the views' projected screen means when a strategy has :attr:`Strategy.screen_grads` (else
            ``None``): one ``[b_i,N,2]`` per op call, the views in order; after the backward their ``grad`` is each
            view's own screen-space gradient.
    """

    indices: list[int]
    image: torch.Tensor
    alpha: torch.Tensor
    share: int
    means2d: list[torch.Tensor] | None = None


class Strategy:
    """An optional part of the fitter; every hook does nothing unless overridden.

    The fitter calls, per step: :meth:`loss` and then :meth:`after_backward` for every render (one or several
    views, :class:`ViewRender`), and :meth:`after_step` after Adam's step (before the learning-rate schedule's
    epoch step). Strategies run in the order the fitter lists them.
    """

    #: The strategy needs each view's own gradient (:meth:`after_backward` after every single view): the
    #: fitter then renders one view per op call.
    per_view: bool = False
    #: The strategy reads each view's screen-space gradient (:attr:`ViewRender.means2d`), which one op call over
    #: several views keeps apart per camera.
    screen_grads: bool = False

    def attach(self, scene: SurfelScene, views: PosedViews | None) -> dict[str, nn.Module]:
        """Check that the strategy applies to ``scene`` (and ``views`` when given), raising
        :class:`nsplat.config.ConfigError` naming its setting otherwise; return the per-point state to
        checkpoint, by module name."""
        return {}

    def loss(self, fit: FitState, view: ViewRender) -> torch.Tensor | None:
        """An extra loss term of the rendered views, summed over them (added to their L1 before the division
        by ``view.share``)."""
        return None

    def after_backward(self, fit: FitState, view: ViewRender) -> None:
        """After the rendered views' backward (the scene's gradients hold the step's views so far)."""

    def after_step(self, fit: FitState, step: int) -> dict[str, float]:
        """After Adam's step ``step`` (0-based); may add, move or remove points. Returns scalars to log."""
        return {}
