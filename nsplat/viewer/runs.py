"""A run folder as a :class:`~nsplat.render.view_model.ViewModel`, for the ``view`` and ``export`` commands.

:func:`load_run` reads a run folder (its ``config.yaml`` and latest checkpoint) and asks the run's task
for its view (the ``view`` function of the task contract, :mod:`nsplat.tasks`): the viewer knows the
tasks only through their registry.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.render.view_model import ViewModel
from nsplat.run.checkpoint import NoCheckpoint
from nsplat.run.context import RunContext
from nsplat.tasks import get_task


class RunError(ValueError):
    """The run folder cannot be viewed or exported (missing, no config, no checkpoint)."""


def read_run_config(run_dir: Path) -> tuple[str, Any]:
    """``(task name, resolved config)`` of a run folder; raises :class:`RunError` when unusable."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"--run {run_dir}: no such run folder")
    if not (run_dir / "config.yaml").is_file():
        raise RunError(f"--run {run_dir}: not a run folder (no config.yaml)")
    raw = read_yaml(run_dir / "config.yaml")
    if "task" not in raw:
        raise RunError(f"--run {run_dir}: config.yaml has no 'task' key")
    try:
        task = get_task(raw["task"])
        return raw["task"], load_config(task.Config, raw, [])
    except ConfigError as exc:
        raise RunError(f"--run {run_dir}: {exc}") from exc


def load_run(run_dir: Path, device: torch.device | str = "cpu", points: bool = False) -> ViewModel:
    """The trained scene of ``run_dir`` (any task with a ``view``) as a :class:`ViewModel` on ``device``.

    A training task (one with ``build``) is viewed at its latest checkpoint (a point-only neural run: its
    ``geometry.ply``); without one, :class:`RunError`.
    ``points``: the run's point-only model instead (its ``point_view``, where the task has one: the neural
    task's stage-1 surfels with their colour), for exports that store a colour per point.
    """
    run_dir = Path(run_dir)
    name, cfg = read_run_config(run_dir)
    task = get_task(name)
    if not hasattr(task, "view"):
        raise RunError(f"--run {run_dir}: task {name!r} has no viewer")
    ctx = RunContext(run_dir=run_dir, device=torch.device(device), seed=int(getattr(cfg, "seed", 0)), resume=True)
    if points and hasattr(task, "point_view"):
        return task.point_view(cfg, ctx)
    try:
        return task.view(cfg, ctx)
    except NoCheckpoint:
        raise RunError(f"--run {run_dir}: no checkpoint yet (train first, or wait for the first checkpoint)") from None
