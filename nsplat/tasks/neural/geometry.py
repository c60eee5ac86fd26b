"""Stage 1 of the neural task: the initial surfels (:mod:`~nsplat.tasks.neural.starts`) fitted to the training
views (:func:`fit_geometry`). A fit whose val PSNR neither rises nor beats a flat image within
``geometry.stall_epochs`` stops with a :class:`~nsplat.errors.DataError` that says where the surfels are and what
to set (:mod:`~nsplat.tasks.neural.diagnosis`)."""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any

import torch

from nsplat.data.views import PosedViews
from nsplat.errors import DataError
from nsplat.evaluation.image_metrics import psnr
from nsplat.fitting import fit
from nsplat.render import renderer as gateway
from nsplat.run import distributed
from nsplat.run.context import RunContext
from nsplat.run.engine import write_json
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.capture import prepare
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.diagnosis import GAP_DB, STALL_DB, STALL_MIN_STEPS, gap_message, stall_message
from nsplat.tasks.neural.starts import initial_geometry

log = logging.getLogger(__name__)


def fit_geometry(cfg: Config, ctx: RunContext, train: PosedViews, val: PosedViews | None = None) -> SurfelScene:
    """Stage 1: initial points, fitted to ``train`` with the op (resumable); writes ``geometry.ply``.

    With ``geometry.log.validate > 0`` and ``val``, the stage-1 surfels are rendered on ``val``
    (``eval.val_views`` of them, evaluation settings, the mean of ``eval.draws`` draws) at that cadence
    and ``geometry_history.json`` records ``{step, elapsed_s, val_psnr}``; ``elapsed_s`` is the stage's
    wall time so far, from before the initial points, without the validation renders (the time-to-quality
    curve of stage 1)."""
    t0, validating = time.perf_counter(), 0.0
    if cfg.data.is_capture() and distributed.is_main():
        write_json(ctx.run_dir / "capture_frame.json", prepare(cfg).frame.diagnosis())
    scene = initial_geometry(cfg, train, ctx.seed)
    g = cfg.geometry
    history: list[dict[str, float]] = []
    val_sub = val.spread(cfg.eval.val_views) if val is not None else None
    steps_per_epoch = math.ceil(len(train) / g.optim.batch)

    def render_psnr(views: PosedViews | None = None) -> float:
        views = val_sub if views is None else views
        with torch.no_grad():
            rgb = gateway.render_views(scene, views.viewmats, views.Ks, views.width, views.height,
                                       cfg.eval_render(), seed=cfg.eval_seed(), shading=g.optim.shading,
                                       background=views.background, draws=cfg.eval.draws).clamp(0, 1)
        return float(psnr(rgb, views.images).mean())

    stall = None  # (start PSNR, flat-image PSNR) until the check has run
    if val_sub is not None and g.log.validate > 0 and g.stall_epochs > 0 and not ctx.resume:
        flat = val_sub.images.flatten(0, 2).mean(0).expand_as(val_sub.images)
        stall = (render_psnr(), float(psnr(flat, val_sub.images).mean()))

    def validate(done: int, writer: Any) -> dict[str, float]:
        nonlocal validating, stall
        t1 = time.perf_counter()
        value = render_psnr()
        history.append({"step": done, "elapsed_s": t1 - t0 - validating, "val_psnr": value})
        write_json(ctx.run_dir / "geometry_history.json", {"history": history})
        validating += time.perf_counter() - t1
        if stall is not None and done >= max(g.stall_epochs * steps_per_epoch, STALL_MIN_STEPS):
            start, flat = stall
            stall = None
            if value < start + STALL_DB and value < flat + STALL_DB:
                raise DataError(stall_message(cfg, scene, train, done / steps_per_epoch, value, start, flat))
        return {"psnr/val": value}

    if g.optim.epochs > 0:
        fit(scene, train, g.optim, cfg.render, ctx.run_dir / "geometry", seed=ctx.seed, resume=ctx.resume,
            log=dataclasses.replace(g.log, progress=cfg.log.progress), background=train.background,
            desc="geometry", validate=validate if val_sub is not None and g.log.validate > 0 else None)
    if distributed.is_main() and cfg.data.is_capture() and history and g.optim.epochs > 0:
        trained = render_psnr(train.spread(cfg.eval.val_views))
        if (gap := trained - history[-1]["val_psnr"]) > GAP_DB:
            log.warning("stage 1 fits the training photos far better than it predicts the others: %s", gap_message(
                cfg, trained, history[-1]["val_psnr"], gap))
    if distributed.is_main():
        scene.save_ply(ctx.run_dir / "geometry.ply")
    return scene
