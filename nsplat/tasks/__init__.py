"""Task registry and the task contract.

The config file's top-level ``task`` key selects a module; the CLI (:mod:`nsplat.cli`) dispatches to it.
A task module satisfies :class:`Task` (docs/architecture.md "Adding a task"): everything every task does
the same way (loop, cadences, checkpoints, resume, seeds, JSON) is the engine's (:mod:`nsplat.run.engine`),
every render goes through :mod:`nsplat.render.renderer`, every loader returns :class:`nsplat.data.PosedViews`.
"""
from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any, Protocol

from nsplat.config import ConfigError
from nsplat.render.view_model import ViewModel
from nsplat.run.context import RunContext

TASKS: dict[str, str] = {
    "refine": "nsplat.tasks.refine",
    "demo": "nsplat.tasks.demo",
    "reconstruct": "nsplat.tasks.reconstruct",
    "neural": "nsplat.tasks.neural",
}


class Task(Protocol):
    """What a task module provides.

    Attributes:
        Config: its config dataclass (strict YAML + overrides, :mod:`nsplat.config`), with sections
            ``render`` (:class:`nsplat.render.renderer.RenderConfig`) and ``log``
            (:class:`nsplat.run.engine.LogConfig`).

    Besides the methods below, a training task has ``build(cfg, ...) -> nsplat.run.engine.Trainables`` (its
    modules and optimisers; the allocation table builds through it) and a ``step`` function of its own
    signature that the engine calls once per step (``Engine.train(trainables, step)``): tasks keep their
    own step (GAN, alternating groups and pruning, per-view backward). Its ``run`` hands the engine a
    cheap live-view builder (``Engine.train(..., view=)``: a :class:`nsplat.render.view_model.ViewModel` of the
    current state).
    """

    Config: type

    def run(self, cfg: Any, ctx: RunContext) -> Any:
        """The ``train`` command: load data, ``build``, run the engine over ``step``, write outputs."""

    def evaluate(self, cfg: Any, ctx: RunContext, split: str = "test") -> Any:
        """The ``eval`` command on the run's latest checkpoint."""

    def render(self, cfg: Any, ctx: RunContext) -> Any:
        """The ``render`` command (images or video of the run's latest checkpoint). A task whose module sets
        ``RENDER_PATHS = True`` takes a third argument, the command's :class:`nsplat.render.video.RenderRequest`
        (camera path, outputs, frame rate, frames, resolution); the CLI refuses those options for the others.
        A task may also provide ``point_view(cfg, ctx) -> ViewModel``: its point-only model with a colour per
        point, which ``export --format 3dgs`` writes when ``view``'s features are not a colour."""

    def view(self, cfg: Any, ctx: RunContext) -> ViewModel:
        """The ``view`` and ``export`` commands: the run's latest checkpoint (a task without ``build``:
        its configured scene) as a :class:`nsplat.render.view_model.ViewModel` on ``ctx.device``. The viewer
        calls it through :func:`get_task`; tasks never import :mod:`nsplat.viewer`."""


def get_task(name: str) -> ModuleType:
    """Import the module of task ``name``; unknown names raise :class:`ConfigError` listing the valid ones."""
    if name not in TASKS:
        raise ConfigError(f"task: unknown task {name!r}; expected one of {sorted(TASKS)}")
    return importlib.import_module(TASKS[name])
