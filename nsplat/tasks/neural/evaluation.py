"""Evaluation of the neural task: renders of a split (:func:`render_split`), held-out metrics with PNGs
(:func:`evaluate_split`), stage 1 alone (:func:`evaluate_geometry`) and the orbit video (:func:`write_orbit`)."""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import imageio
import imageio.v3 as iio
import numpy as np
import torch

from nsplat.cameras import look_at
from nsplat.data.views import PosedViews
from nsplat.engine import write_json
from nsplat.comparison_sheet import write_sheet
from nsplat.eval_protocol import protocol_images, score_views, summary, summary_text, write_per_view_csv
from nsplat.metrics_image import error_share, silhouette_band
from nsplat.render import RenderConfig, render_views
from nsplat.report import results
from nsplat.runctx import RunContext
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.geometry import geometry_scene_config
from nsplat.tasks.neural.model import NeuralRenderer

log = logging.getLogger(__name__)


#: Extensions a view name may carry (COLMAP image names keep theirs).
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr"}


def _stats(x: torch.Tensor) -> dict[str, float]:
    x = x.double()
    return {"mean": float(x.mean()), "std": float(x.std(unbiased=False)) if x.numel() > 1 else 0.0}


def _png(x: torch.Tensor) -> np.ndarray:
    return (x.detach().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def _band(rgb: torch.Tensor, views: PosedViews, width: int = 1) -> dict | None:
    """Where the error sits: the share of pixels within ``width`` px of a silhouette edge and their share
    of the squared error (``None`` without coverage masks)."""
    if views.masks is None:
        return None
    band = silhouette_band(views.masks.float(), width)
    return {"width_px": width, "pixel_share": float(band.float().mean()),
            "error_share": _stats(error_share(rgb, views.images, band))}


@torch.no_grad()
def render_split(model: NeuralRenderer, views: PosedViews, seed: int, batch: int = 4,
                 render_cfg: RenderConfig | None = None, draws: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendered RGB ``[B,H,W,3]`` and feature images ``[B,C',H,W]`` of all ``views`` (eval mode), with the
    render settings ``render_cfg`` (default: the model's, i.e. training's; see ``Config.eval_render``) and
    ``draws`` averaged op draws per feature image (``eval.draws``)."""
    was, trained_cfg = model.training, model.render_cfg
    model.eval()
    if render_cfg is not None:
        model.render_cfg = render_cfg
    rgbs, conds = [], []
    try:
        for s in range(0, len(views), batch):
            rgb, cond = model(views.viewmats[s:s + batch], views.Ks[s:s + batch], views.width, views.height, seed + s,
                              draws=draws)
            rgbs.append(rgb.permute(0, 2, 3, 1))
            conds.append(cond)
    finally:
        model.train(was)
        model.render_cfg = trained_cfg
    return torch.cat(rgbs).clamp(0, 1), torch.cat(conds)


def evaluate_split(cfg: Config, ctx: RunContext, model: NeuralRenderer, views: PosedViews, split: str,
                   seed: int) -> dict:
    """Score every view of ``views`` (split ``split``) under ``eval.protocol`` (:mod:`nsplat.eval_protocol`),
    rendered on the configured background with op seed ``seed``.

    Writes to ``eval_<split>/``: ``metrics.json`` (the protocol, mean ± std per metric), ``per_view.csv``
    and ``per_view.json`` (one row per view), ``sheet.png`` (ground truth | render | error heat map of
    ``eval.sheet_views`` views) and, with ``eval.images``, ``<name>.png`` / ``<name>_gt.png`` per view;
    reports the means on stdout. Returns the metrics dict.
    """
    t0 = time.perf_counter()
    rgb, _ = render_split(model, views, seed=seed, render_cfg=cfg.eval_render(), draws=cfg.eval.draws)
    seconds = time.perf_counter() - t0
    scores = score_views(rgb, views.images, cfg.eval.protocol)
    out_dir = ctx.run_dir / f"eval_{split}"
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = [{"name": name, **{k: float(v[i]) for k, v in scores.per_view.items()}} for i, name in enumerate(views.names)]
    if cfg.eval.images:
        for i, name in enumerate(views.names):
            stem = Path(name).name  # a photo keeps no second extension: im_000.png → im_000.png
            if Path(stem).suffix.lower() in IMAGE_SUFFIXES:
                stem = Path(stem).stem
            iio.imwrite(out_dir / f"{stem}.png", _png(rgb[i]))
            iio.imwrite(out_dir / f"{stem}_gt.png", _png(views.images[i]))
    if cfg.eval.sheet_views:
        shown = protocol_images(rgb, views.images, cfg.eval.protocol)
        write_sheet(out_dir / "sheet.png", views.names, shown[1], shown[0], scores.per_view["psnr"],
                    cfg.eval.sheet_views)
    metrics = {"split": split, "views": len(views), "resolution": [views.width, views.height],
               "background": list(cfg.data.background), "renderer": cfg.eval_render().renderer,
               "draws": cfg.eval.draws, "points": model.scene.num_points, **summary(scores),
               "silhouette_band": _band(rgb, views), "render_seconds": seconds}
    write_json(out_dir / "metrics.json", metrics)
    write_json(out_dir / "per_view.json", {"protocol": scores.protocol, "views": rows})
    write_per_view_csv(out_dir / "per_view.csv", views.names, scores)
    results.info("held-out %s (%d views, %dx%d, %s protocol): %s", split, len(views), views.width, views.height,
                 scores.protocol, summary_text(scores))
    log.info("metrics written to %s", out_dir / "metrics.json")
    return metrics


@torch.no_grad()
def evaluate_geometry(cfg: Config, ctx: RunContext, splits: dict[str, PosedViews], seed: int) -> dict:
    """Stage 1 alone, the point-based baseline the U-Net must beat: the run's ``geometry.ply`` (RGB
    surfels) rendered by the op (evaluation settings, the mean of ``eval.draws`` draws like the U-Net's
    feature images) into each split of ``splits``, scored under ``eval.protocol``; written to
    ``eval_geometry.json`` and returned as ``{"points": N, split: {protocol, psnr, ssim, lpips}}``."""
    scene = SurfelScene.load_ply(ctx.run_dir / "geometry.ply", geometry_scene_config(cfg), device=ctx.device)
    out: dict = {"points": scene.num_points}
    for split, views in splits.items():
        rgbs = [render_views(scene, views.viewmats[s:s + 4], views.Ks[s:s + 4], views.width, views.height,
                             cfg.eval_render(), seed=seed + s, shading=cfg.geometry.optim.shading,
                             background=views.background, draws=cfg.eval.draws)
                for s in range(0, len(views), 4)]
        rgb = torch.cat(rgbs).clamp(0, 1)
        scores = score_views(rgb, views.images, cfg.eval.protocol)
        out[split] = summary(scores)
        results.info("stage 1 alone, %s (%s protocol): %s", split, scores.protocol, summary_text(scores))
    write_json(ctx.run_dir / "eval_geometry.json", out)
    return out


def orbit_cameras(train: PosedViews, frames: int) -> torch.Tensor:
    """``[frames,4,4]`` cameras on a circle at the training cameras' mean distance and elevation,
    looking at the point nearest to all training optical axes, up = mean camera up."""
    V = train.viewmats.double().cpu()
    R, t = V[:, :3, :3], V[:, :3, 3]
    eyes = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    axes = R[:, 2, :]  # camera z (forward) in world coordinates
    up = -R[:, 1, :].mean(0)
    up = up / up.norm()
    # Least-squares point closest to all optical axes.
    P = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    target = torch.linalg.lstsq(P.sum(0), (P @ eyes[..., None]).sum(0)).solution[:, 0]
    rel = eyes - target
    height = float((rel @ up).mean())
    radius = float((rel - (rel @ up)[:, None] * up).norm(dim=-1).mean())
    e1 = torch.linalg.cross(up, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    if e1.norm() < 1e-6:
        e1 = torch.linalg.cross(up, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(up, e1)
    ang = torch.arange(frames, dtype=torch.float64) / frames * 2 * math.pi
    eye = target + radius * (torch.cos(ang)[:, None] * e1 + torch.sin(ang)[:, None] * e2) + height * up
    return look_at(eye, target.expand_as(eye), up).float()


def write_orbit(cfg: Config, ctx: RunContext, model: NeuralRenderer, train: PosedViews, seed: int) -> Path:
    """Write ``orbit.mp4``: ``model`` along a circle of cameras around the training cameras' target."""
    viewmats = orbit_cameras(train, cfg.eval.orbit_frames).to(ctx.device)
    count = viewmats.shape[0]
    orbit = PosedViews(train.images[:1].expand(count, -1, -1, -1), viewmats,
                       train.Ks[:1].expand(count, 3, 3).contiguous(), [f"orbit_{i}" for i in range(count)])
    rgb, _ = render_split(model, orbit, seed=seed, render_cfg=cfg.eval_render(), draws=cfg.eval.draws)
    frames = _png(rgb)
    H, W = frames.shape[1:3]
    frames = np.pad(frames, ((0, 0), (0, H % 2), (0, W % 2), (0, 0)), mode="edge")  # even sizes for yuv420p
    path = ctx.run_dir / "orbit.mp4"
    imageio.mimwrite(path, list(frames), fps=cfg.eval.fps, macro_block_size=1)
    results.info("orbit video (%d frames) written to %s", len(frames), path)
    return path
