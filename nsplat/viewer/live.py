"""Live view while training: ``python train.py ... viewer=true``.

The training loops call :func:`step` once per optimisation step with a cheap *source* (a callable
returning the current :class:`~nsplat.view_model.ViewModel`). Without an active session it is a
no-op. With one, the viser server runs in its own threads (page, websocket, camera messages) and
renders happen in the training thread, between steps, so they always see consistent parameters:

* only when a browser is connected and either its camera moved / waits for the full-quality render,
  or ``refresh_every`` steps passed since the last refresh (to show training progress);
* only while the viewer's total time stays below ``budget`` × the session's wall time, so the
  slow-down of training is bounded by about ``budget``;
* every viewer error is caught and logged; after ``max_errors`` the viewer switches itself off.
  A browser that disconnects is simply no longer rendered for.

Options (config-style overrides, removed before the task's config sees them): ``viewer=true``,
``viewer.host=127.0.0.1``, ``viewer.port=8080``, ``viewer.budget=0.1``, ``viewer.refresh_every=10``,
``viewer.resolution=192``, ``viewer.samples=8``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from typing import Callable, Iterator

from nsplat.config import ConfigError
from nsplat.view_model import ViewModel
from nsplat.viewer.model import RenderSettings
from nsplat.viewer.server import ViewerServer

log = logging.getLogger(__name__)


@dataclasses.dataclass
class LiveOptions:
    """Live-view options (see the module docstring)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 8080
    budget: float = 0.1
    refresh_every: int = 10
    resolution: int = 192
    samples: int = 8
    max_errors: int = 5


def split_overrides(overrides: list[str]) -> tuple[list[str], LiveOptions]:
    """``(the task's overrides, live-view options)``: ``viewer=…`` and ``viewer.<key>=…`` are taken out."""
    rest, opts = [], LiveOptions()
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or not (key == "viewer" or key.startswith("viewer.")):
            rest.append(item)
            continue
        name = "enabled" if key == "viewer" else key[len("viewer."):]
        field = {f.name: f for f in dataclasses.fields(LiveOptions)}.get(name)
        if field is None or name == "max_errors":
            raise ConfigError(f"{key}: unknown viewer option; expected viewer=true|false or viewer.host, "
                              "viewer.port, viewer.budget, viewer.refresh_every, viewer.resolution, viewer.samples")
        try:
            if name == "enabled":
                if value.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(value)
                parsed = value.lower() in ("true", "1", "yes")
            else:
                parsed = type(getattr(opts, name))(value)
        except ValueError:
            raise ConfigError(f"{key}: cannot parse {value!r}") from None
        setattr(opts, name, parsed)
    if any(k.startswith("viewer.") for k in (i.partition("=")[0] for i in overrides)) and not opts.enabled:
        opts.enabled = True  # giving a viewer option asks for the viewer
    if not 0.0 < opts.budget <= 1.0:
        raise ConfigError(f"viewer.budget: expected a fraction in (0, 1], got {opts.budget}")
    return rest, opts


class LiveViewer:
    """The live-view session (a :class:`~nsplat.viewer.server.ViewerServer` without its own render thread)."""

    def __init__(self, opts: LiveOptions) -> None:
        self.opts = opts
        self.server = ViewerServer(None, opts.host, opts.port,
                                   RenderSettings(samples=opts.samples, resolution=opts.resolution), thread=False)
        self.t_start = time.perf_counter()
        self.spent_s = 0.0
        self.renders = 0
        self.errors = 0
        self.last_refresh = -1
        log.info("live viewer: %s (budget %.0f%% of training time)", self.server.url, 100 * opts.budget)

    def step(self, step: int, source: Callable[[], ViewModel]) -> None:
        """Render for the connected browsers if due and within budget (never raises)."""
        if self.server is None:
            return
        t0 = time.perf_counter()
        try:
            first = self.server.model is None
            if first:
                self.server.set_model(source())  # frusta and initial camera for browsers that connect later
                self.last_refresh = step
            if not self.server.server.get_clients():
                return
            if self.spent_s > self.opts.budget * (t0 - self.t_start):
                return
            refresh = step - self.last_refresh >= self.opts.refresh_every
            if not (refresh or self.server.pending()):
                return
            if not first:
                self.server.set_model(source(), refresh=refresh)
            if refresh:
                self.last_refresh = step
            self.renders += self.server.poll()
        except Exception as exc:  # noqa: BLE001 - the viewer must never stop training
            self.errors += 1
            log.warning("live viewer: %s (%d/%d errors)", exc, self.errors, self.opts.max_errors)
            if self.errors >= self.opts.max_errors:
                log.warning("live viewer: switched off after repeated errors; training continues")
                self.close()
        finally:
            self.spent_s += time.perf_counter() - t0

    def close(self) -> None:
        """Stop the server (idempotent, never raises)."""
        server, self.server = self.server, None
        if server is not None:
            try:
                server.close()
            except Exception as exc:  # noqa: BLE001
                log.debug("live viewer: close: %s", exc)


_ACTIVE: LiveViewer | None = None


def step(step: int, source: Callable[[], ViewModel]) -> None:
    """The training loops' hook, one call per optimisation step; a no-op without a live session.

    ``source`` is only called when a render is due (keep it cheap: it wraps the current tensors).
    """
    if _ACTIVE is not None:
        _ACTIVE.step(step, source)


def active() -> LiveViewer | None:
    """The running live viewer, if any."""
    return _ACTIVE


@contextlib.contextmanager
def session(opts: LiveOptions) -> Iterator[LiveViewer | None]:
    """Run a live viewer for the duration of the block (nothing when ``opts.enabled`` is false)."""
    global _ACTIVE
    if not opts.enabled:
        yield None
        return
    viewer = LiveViewer(opts)
    _ACTIVE = viewer
    try:
        yield viewer
    finally:
        _ACTIVE = None
        log.info("live viewer: %d renders, %.2f s in the viewer", viewer.renders, viewer.spent_s)
        viewer.close()
