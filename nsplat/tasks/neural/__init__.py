"""Task ``neural``: neural point rendering (paper §4 "Neural Rendering").

Stage 1 (geometry, :mod:`~nsplat.tasks.neural.geometry`): RGB surfels initialised on the visual hull of the
training silhouettes (or the SfM points of a capture, a PLY, random points; :mod:`~nsplat.tasks.neural.starts`)
and fitted to the training views with the op (:func:`nsplat.fitting.fit`); written to ``geometry.ply``. A start
the cameras cannot see, or a fit that learns nothing, stops with a diagnosis (:mod:`~nsplat.tasks.neural.diagnosis`).

Stage 2 (neural, :mod:`~nsplat.tasks.neural.training`): every point gets ``C`` learned features (the first
three start from its stage-1 colour); the op splats them (plus coverage) into a feature image that a U-Net
shader turns into RGB (:mod:`~nsplat.tasks.neural.model`), trained with ``λ_L1·(L1 + D-SSIM) + adversarial``
against a conditional PatchGAN. ``neural.steps: 0`` skips it: the stage-1 surfels are the model.

Evaluation (:mod:`~nsplat.tasks.neural.evaluation`): held-out PSNR/SSIM with PNGs, stage 1 alone, the orbit
video. Data (:mod:`~nsplat.tasks.neural.data`): the procedural scene, NeRF-synthetic folders and COLMAP
captures (:mod:`~nsplat.tasks.neural.capture`). Configuration: :mod:`~nsplat.tasks.neural.config`.

Both stages run on the engine (:mod:`nsplat.run.engine`), data-parallel under torchrun
(:mod:`nsplat.run.distributed`, docs/distributed.md); rank 0 alone writes the run folder and evaluates.

Run folder: ``config.yaml``, ``geometry/`` (stage-1 logs and checkpoints), ``geometry.ply``,
``tb/`` (TensorBoard), ``checkpoints/`` (stage 2, atomic, exact resume), ``history.json`` (train
and val PSNR over steps), ``eval_<split>/`` (``metrics.json``, ``per_view.csv`` and ``.json``, ``sheet.png``, PNGs),
``eval_geometry.json`` (stage 1 alone on val and the held-out split), ``finished.json`` and the ``render``
command's videos (``orbit.mp4``, ``test.mp4``, ``train-smooth_depth.mp4``, ...).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import torch

from nsplat.config import ConfigError
from nsplat.data.views import PosedViews
from nsplat.render.video import RenderRequest
from nsplat.render.view_model import ViewModel, cameras_of, surfel_view
from nsplat.run import distributed
from nsplat.run.context import RunContext, RunFolderError
from nsplat.run.engine import Engine, checkpoint_rows, latest_payload, write_json
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.capture import with_capture_render
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.evaluation import evaluate_geometry, evaluate_split, write_path_videos
from nsplat.tasks.neural.geometry import fit_geometry
from nsplat.tasks.neural.model import Renderer, load_model, neural_scene_config, neural_scene_from, neural_view
from nsplat.tasks.neural.starts import geometry_scene_config
from nsplat.tasks.neural.training import build, check_parallel, train_neural

__all__ = ["Config", "DISTRIBUTED", "build", "evaluate", "point_view", "render", "run", "view"]

log = logging.getLogger(__name__)

#: Runs data-parallel under torchrun (the CLI refuses tasks without this flag).
DISTRIBUTED = True
#: ``render`` takes a :class:`nsplat.render.video.RenderRequest` (camera path, outputs, fps, frames, resolution).
RENDER_PATHS = True


def run(cfg: Config, ctx: RunContext) -> dict:
    """Train (stage 1, then stage 2; resumable) and evaluate the held-out split (under torchrun: rank 0
    evaluates and returns the metrics, the other ranks return ``{}`` after training)."""
    cfg = with_capture_render(cfg)
    torch.manual_seed(ctx.seed)
    t0 = time.perf_counter()
    train = load_views(cfg, "train", ctx.device)
    check_parallel(cfg, len(train))
    val = load_views(cfg, "val", ctx.device) if cfg.log.validate else None
    payload = latest_payload(ctx.run_dir, ctx.resume, "cpu")
    timing = {}
    if payload is None:
        geo = fit_geometry(cfg, ctx, train, val)
        timing["geometry_s"] = time.perf_counter() - t0
        if cfg.neural.steps == 0:
            return _point_only_result(cfg, ctx, val, timing)
        scene = neural_scene_from(cfg, geo, seed=ctx.seed)
        log.info("stage 2: %d points, %d features", scene.num_points, cfg.neural.features)
    else:
        points = checkpoint_rows(payload, "model", "scene._means")
        scene = SurfelScene(neural_scene_config(cfg), points, device=ctx.device)
    t = build(cfg, scene, ctx.seed)
    start = Engine(ctx.run_dir, cfg.log, cfg.neural.steps).resume(t, payload)
    train_neural(cfg, ctx, t, train, val, start)
    if not distributed.is_main():
        return {}
    timing["train_total_s"] = time.perf_counter() - t0
    metrics = evaluate(cfg, ctx, cfg.eval.split, model=t.modules["model"])
    if cfg.eval.geometry:
        splits = {"val": val if val is not None else load_views(cfg, "val", ctx.device),
                  cfg.eval.split: load_views(cfg, cfg.eval.split, ctx.device)}
        evaluate_geometry(cfg, ctx, splits, cfg.eval_seed())
    write_json(ctx.run_dir / "timing.json", {**timing, "neural_steps_s": float(t.extra.get("seconds", 0.0))})
    return metrics


def _point_only_result(cfg: Config, ctx: RunContext, val: PosedViews | None, timing: dict) -> dict:
    """``neural.steps: 0``: the stage-1 surfels are the model; their held-out metrics (``eval_<split>/``, as a
    stage-2 run writes them, and ``eval_geometry.json`` with the validation split) are the run's."""
    if not distributed.is_main():
        return {}
    splits = {"val": val if val is not None else load_views(cfg, "val", ctx.device),
              cfg.eval.split: load_views(cfg, cfg.eval.split, ctx.device)}
    evaluate_geometry(cfg, ctx, splits, cfg.eval_seed())
    metrics = evaluate(cfg, ctx, cfg.eval.split)
    write_json(ctx.run_dir / "timing.json", {**timing, "train_total_s": timing["geometry_s"], "neural_steps_s": 0.0})
    return metrics


def evaluate(cfg: Config, ctx: RunContext, split: str = "test", model: Renderer | None = None) -> dict:
    """Held-out metrics of ``split`` (:func:`nsplat.tasks.neural.evaluation.evaluate_split`) of ``model``, by
    default the run's (:func:`~nsplat.tasks.neural.model.load_model`: stage 2, or stage 1 of a point-only run)."""
    if split not in ("train", "val", "test"):
        raise ConfigError(f"--split: expected train, val or test, got {split!r}")
    cfg = with_capture_render(cfg)
    model = model if model is not None else load_model(cfg, ctx)
    return evaluate_split(cfg, ctx, model, load_views(cfg, split, ctx.device), split, cfg.eval_seed())


def render(cfg: Config, ctx: RunContext, request: RenderRequest | None = None) -> list[Path]:
    """Videos of the trained model along a camera path, one per output (default: ``orbit.mp4``, RGB along a
    circle of cameras around the scene; :class:`nsplat.render.video.RenderRequest`, :func:`write_path_videos`)."""
    cfg = with_capture_render(cfg)
    return write_path_videos(cfg, ctx, load_model(cfg, ctx), request or RenderRequest())


def point_view(cfg: Config, ctx: RunContext) -> ViewModel:
    """The point-only model for exports that store a colour per point (``export --format 3dgs``): stage 1's
    surfels (``geometry.ply``) with their RGB or view-dependent SH colour and the training cameras (the 3DGS
    export's kernel conversion averages over them, :mod:`nsplat.gaussians.kernel`)."""
    path = ctx.run_dir / "geometry.ply"
    if not path.is_file():
        raise RunFolderError(f"--run {ctx.run_dir}: no geometry.ply yet (stage 1 has not finished)")
    scene = SurfelScene.load_ply(path, geometry_scene_config(cfg), device=ctx.device)
    background = torch.tensor(cfg.data.background, dtype=scene.means.dtype, device=ctx.device)
    train = load_views(cfg, "train", ctx.device)
    return surfel_view(scene, cameras_of(train.images, train.viewmats, train.Ks), shading=cfg.geometry.optim.shading,
                       background=background, render_cfg=cfg.eval_render(), task="neural", seed=cfg.eval_seed())


def view(cfg: Config, ctx: RunContext) -> ViewModel:
    """The task contract's ``view``: the trained renderer (eval mode) with the training cameras; for a
    point-only run (``neural.steps: 0``) stage 1's surfels (:func:`point_view`)."""
    if cfg.neural.steps == 0:
        return point_view(cfg, ctx)
    train = load_views(cfg, "train", ctx.device)
    return neural_view(load_model(cfg, ctx).eval(), cameras_of(train.images, train.viewmats, train.Ks),
                       seed=cfg.eval_seed())
