"""The web viewer's settings, one section for both ways of starting it.

``python train.py view --run DIR viewer.port=9000`` serves a finished run; ``python train.py … viewer=true
viewer.port=9000`` serves the run while it trains. Both read :class:`ViewerConfig` from the same ``viewer.<key>``
overrides (:func:`split_viewer_overrides`), which never reach the task's config. The viewer renders with the
run's own ``render`` settings (samples, ε, …); ``viewer.render.<key>`` overrides them for the viewer only, under
their ``render`` names, as ``eval.render`` does for evaluation.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from nsplat.config import ConfigError, from_dict, parse_override, require, require_fields, to_dict
from nsplat.render.renderer import RenderConfig


@dataclasses.dataclass
class ViewerConfig:
    """The viewer's settings (``viewer.<key>=value`` on the command line).

    Attributes:
        enabled: serve the run while it trains (training commands; ``viewer=true``; any ``viewer.<key>``
            override turns it on).
        host: address to listen on (``127.0.0.1``: this machine only; ``0.0.0.0``: every interface).
        port: TCP port of the page.
        resolution: longest image side (px) of a browser camera's full-quality render.
        render: overrides of the run's ``render`` section for the viewer's renders (e.g. ``{samples: 8}``); the
            panel starts from them. Empty: the run's own settings.
        refresh_every: while training, re-render the connected browsers every this many steps.
        budget: while training, the viewer's largest share of the wall time, in (0, 1].
    """

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 8080
    resolution: int = 256
    render: dict[str, Any] = dataclasses.field(default_factory=dict)
    refresh_every: int = 10
    budget: float = 0.1

    def __post_init__(self) -> None:
        require_fields(self, port=">=1", refresh_every=">=1", budget="prob")
        require(self.resolution >= 8, "resolution", "at least 8 pixels", self.resolution)
        require(self.port <= 65535, "port", "a TCP port (1..65535)", self.port)
        self.render_cfg(RenderConfig())  # unknown or invalid render keys fail at load

    def render_cfg(self, base: RenderConfig) -> RenderConfig:
        """The viewer's render settings: ``base`` (the run's) with the ``render`` overrides applied."""
        if not self.render:
            return base
        return from_dict(RenderConfig, {**to_dict(base), **self.render}, prefix="viewer.render.")


def split_viewer_overrides(overrides: list[str]) -> tuple[list[str], ViewerConfig]:
    """``(the task's overrides, the viewer's settings)``: ``viewer=…`` and ``viewer.<key>=…`` are taken out and
    read into :class:`ViewerConfig` (errors name the dotted key, e.g. ``viewer.port``)."""
    rest: list[str] = []
    data: dict[str, Any] = {}
    for item in overrides:
        path, value = parse_override(item)
        if path[0] != "viewer":
            rest.append(item)
            continue
        if len(path) == 1:
            data["enabled"] = value
            continue
        node = data
        for part in path[1:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r}: 'viewer.{part}' is not a section")
        node[path[-1]] = value
    if data and "enabled" not in data:
        data["enabled"] = True  # giving a viewer setting asks for the viewer
    return rest, from_dict(ViewerConfig, data, prefix="viewer.")
