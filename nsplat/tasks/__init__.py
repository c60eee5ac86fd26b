"""Task registry: each task module exposes ``Config`` (a dataclass) and ``run(cfg, ctx)``.

The config file's top-level ``task`` key selects the module; ``train.py`` dispatches here. A task
module may also expose ``evaluate(ctx, split)`` and ``render(ctx)`` for the ``eval``/``render``
sub-commands.
"""
from __future__ import annotations

import importlib
from types import ModuleType

from nsplat.config import ConfigError

TASKS: dict[str, str] = {
    "refine": "nsplat.tasks.refine",
    "demo": "nsplat.tasks.demo",
    "reconstruct": "nsplat.tasks.reconstruct",
    "neural": "nsplat.tasks.neural",
}


def get_task(name: str) -> ModuleType:
    """Import the module of task ``name``; unknown names raise :class:`ConfigError` listing the valid ones."""
    if name not in TASKS:
        raise ConfigError(f"task: unknown task {name!r}; expected one of {sorted(TASKS)}")
    return importlib.import_module(TASKS[name])
