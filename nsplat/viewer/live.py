"""Live view while training: ``python train.py ... viewer=true``.

The training loops call :func:`step` once per optimisation step with a cheap *source* (a callable
returning the current :class:`~nsplat.render.view_model.ViewModel`). Without an active session it is a
no-op. With one, the viser server runs in its own threads (page, websocket, camera messages) and
renders happen in the training thread, between steps, so they always see consistent parameters:

* only when a browser is connected and either its camera moved / waits for the full-quality render,
  or ``refresh_every`` steps passed since the last refresh (to show training progress);
* only while the viewer's total time stays below ``budget`` × the session's wall time, so the
  slow-down of training is bounded by about ``budget``;
* every viewer error is caught and logged; after :data:`MAX_ERRORS` the viewer switches itself off.
  A browser that disconnects is simply no longer rendered for.

Settings: :class:`nsplat.viewer.config.ViewerConfig` (``viewer=true``, ``viewer.port=…``, ``viewer.budget=…``,
``viewer.render.samples=…``; taken out of the overrides before the task's config sees them).
"""
from __future__ import annotations

import contextlib
import logging
import time
from typing import Callable, Iterator

from nsplat.render.view_model import ViewModel
from nsplat.viewer.config import ViewerConfig
from nsplat.viewer.server import ViewerServer

log = logging.getLogger(__name__)


#: Viewer errors after which the live viewer switches itself off (training goes on).
MAX_ERRORS = 5


class LiveViewer:
    """The live-view session (a :class:`~nsplat.viewer.server.ViewerServer` without its own render thread)."""

    def __init__(self, cfg: ViewerConfig) -> None:
        self.cfg = cfg
        self.server = ViewerServer(None, cfg, thread=False)
        self.t_start = time.perf_counter()
        self.spent_s = 0.0
        self.renders = 0
        self.errors = 0
        self.last_refresh = -1
        log.info("live viewer: %s (budget %.0f%% of training time)", self.server.url, 100 * cfg.budget)

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
            if self.spent_s > self.cfg.budget * (t0 - self.t_start):
                return
            refresh = step - self.last_refresh >= self.cfg.refresh_every
            if not (refresh or self.server.pending()):
                return
            if not first:
                self.server.set_model(source(), refresh=refresh)
            if refresh:
                self.last_refresh = step
            self.renders += self.server.poll()
        except Exception as exc:  # noqa: BLE001 - the viewer must never stop training
            self.errors += 1
            log.warning("live viewer: %s (%d/%d errors)", exc, self.errors, MAX_ERRORS)
            if self.errors >= MAX_ERRORS:
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
def session(cfg: ViewerConfig) -> Iterator[LiveViewer | None]:
    """Run a live viewer for the duration of the block (nothing when ``cfg.enabled`` is false)."""
    global _ACTIVE
    if not cfg.enabled:
        yield None
        return
    viewer = LiveViewer(cfg)
    _ACTIVE = viewer
    try:
        yield viewer
    finally:
        _ACTIVE = None
        log.info("live viewer: %d renders, %.2f s in the viewer", viewer.renders, viewer.spent_s)
        viewer.close()
