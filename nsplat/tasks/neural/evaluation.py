"""Evaluation of the neural task: renders of cameras and splits (:func:`render_cameras`, :func:`render_split`),
held-out metrics under the evaluation protocol with a per-view table and a comparison sheet
(:func:`evaluate_split`), stage 1 alone (:func:`evaluate_geometry`) and videos along camera paths
(:func:`write_path_videos`: orbit, the test views, a smooth path through the training cameras, a nerfstudio
camera path; RGB, depth, normal, alpha)."""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from tqdm import tqdm

from nsplat.data.paths import resolve
from nsplat.data.views import PosedViews
from nsplat.evaluation.comparison_sheet import write_sheet
from nsplat.evaluation.image_metrics import error_share, silhouette_band
from nsplat.evaluation.protocol import protocol_images, score_views, summary, summary_text, write_per_view_csv
from nsplat.render.camera_paths import CameraPath, orbit, read_nerfstudio_path, smooth_path
from nsplat.render.renderer import RenderConfig, render_geometry, render_views
from nsplat.render.video import RenderRequest, depth_picture, normal_picture, to_uint8, write_video
from nsplat.run.context import RunContext
from nsplat.run.engine import write_json
from nsplat.run.report import results
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.capture import to_training_frame
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.model import Renderer
from nsplat.tasks.neural.starts import geometry_scene_config

log = logging.getLogger(__name__)


#: Extensions a view name may carry (COLMAP image names keep theirs).
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr"}


def _stats(x: torch.Tensor) -> dict[str, float]:
    x = x.double()
    return {"mean": float(x.mean()), "std": float(x.std(unbiased=False)) if x.numel() > 1 else 0.0}


def _band(rgb: torch.Tensor, views: PosedViews, width: int = 1) -> dict | None:
    """Where the error sits: the share of pixels within ``width`` px of a silhouette edge and their share
    of the squared error (``None`` without coverage masks)."""
    if views.masks is None:
        return None
    band = silhouette_band(views.masks.float(), width)
    return {"width_px": width, "pixel_share": float(band.float().mean()),
            "error_share": _stats(error_share(rgb, views.images, band))}


@torch.no_grad()
def render_cameras(model: Renderer, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                   seed: int, batch: int = 4, render_cfg: RenderConfig | None = None, draws: int = 1,
                   progress: tqdm | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendered RGB ``[B,H,W,3]`` and feature images ``[B,C',H,W]`` of the cameras ``viewmats [B,4,4]``,
    ``Ks [B,3,3]`` (eval mode, ``batch`` cameras per call, the call starting at camera ``s`` with op seed
    ``seed + s``), with the render settings ``render_cfg`` (default: the model's, i.e. training's; see
    ``Config.eval_render``) and ``draws`` averaged op draws per feature image (``eval.draws``); ``progress``
    advances by one per camera."""
    was, trained_cfg = model.training, model.render_cfg
    model.eval()
    if render_cfg is not None:
        model.render_cfg = render_cfg
    rgbs, conds = [], []
    try:
        for s in range(0, viewmats.shape[0], batch):
            rgb, cond = model(viewmats[s:s + batch], Ks[s:s + batch], width, height, seed + s, draws=draws)
            rgbs.append(rgb.permute(0, 2, 3, 1))
            conds.append(cond)
            if progress is not None:
                progress.update(rgb.shape[0])
    finally:
        model.train(was)
        model.render_cfg = trained_cfg
    return torch.cat(rgbs).clamp(0, 1), torch.cat(conds)


def render_split(model: Renderer, views: PosedViews, seed: int, batch: int = 4,
                 render_cfg: RenderConfig | None = None, draws: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`render_cameras` of all ``views``."""
    return render_cameras(model, views.viewmats, views.Ks, views.width, views.height, seed, batch, render_cfg, draws)


def evaluate_split(cfg: Config, ctx: RunContext, model: Renderer, views: PosedViews, split: str,
                   seed: int) -> dict:
    """Score every view of ``views`` (split ``split``) under ``eval.protocol`` (:mod:`nsplat.evaluation.protocol`),
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
    rows = [{"name": name, **{k: float(v[i]) for k, v in scores.per_view.items()}}
            for i, name in enumerate(views.names)]
    if cfg.eval.images:
        for i, name in enumerate(views.names):
            stem = Path(name).name  # a photo keeps no second extension: im_000.png → im_000.png
            if Path(stem).suffix.lower() in IMAGE_SUFFIXES:
                stem = Path(stem).stem
            iio.imwrite(out_dir / f"{stem}.png", to_uint8(rgb[i]))
            iio.imwrite(out_dir / f"{stem}_gt.png", to_uint8(views.images[i]))
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


def path_cameras(cfg: Config, ctx: RunContext, request: RenderRequest) -> CameraPath:
    """The cameras of ``request.path`` (:class:`nsplat.render.video.RenderRequest`) in the training frame, at the
    training images' size (a camera path file: its own) or ``request.resolution``."""
    train = load_views(cfg, "train", ctx.device)
    frames = request.frames or cfg.eval.orbit_frames
    if request.path == "test":
        views = load_views(cfg, "test", ctx.device)
        path = CameraPath(views.viewmats, views.Ks, views.width, views.height)
    elif request.path in ("orbit", "train-smooth"):
        V = orbit(train.viewmats, frames) if request.path == "orbit" else smooth_path(train.viewmats, frames)[0]
        path = CameraPath(V, train.Ks[:1].expand(frames, 3, 3).contiguous(), train.width, train.height)
    else:
        path = read_nerfstudio_path(resolve(request.path, base=Path.cwd()))  # a command-line path: from here
        path = dataclasses.replace(path, viewmats=to_training_frame(cfg, path.viewmats))
    path = dataclasses.replace(path, viewmats=path.viewmats.to(ctx.device), Ks=path.Ks.to(ctx.device))
    return path.resized(request.resolution) if request.resolution else path


@torch.no_grad()
def write_path_videos(cfg: Config, ctx: RunContext, model: Renderer, request: RenderRequest) -> list[Path]:
    """Render ``model`` along ``request.path`` (evaluation settings, op seed ``eval_seed() + frame``) and write one
    video per output to the run folder: ``<name>.mp4`` (RGB), ``<name>_depth.mp4``, ``<name>_normal.mp4``,
    ``<name>_alpha.mp4`` (:mod:`nsplat.render.video`). Returns the written paths."""
    path = path_cameras(cfg, ctx, request)
    seed, rc, F = cfg.eval_seed(), cfg.eval_render(), len(path)
    fps = request.fps or path.fps or cfg.eval.fps
    pictures: dict[str, list[np.ndarray]] = {o: [] for o in request.outputs}
    depths: list[tuple[torch.Tensor, torch.Tensor]] = []  # one colour scale for the whole video: kept until the end
    s = model.scene
    with tqdm(total=F, desc=f"render {request.name}", unit="frame", disable=not cfg.log.progress) as bar:
        for i in range(0, F, 4):
            V, K = path.viewmats[i:i + 4], path.Ks[i:i + 4]
            if "rgb" in request.outputs:
                rgb, _ = render_cameras(model, V, K, path.width, path.height, seed + i, render_cfg=rc,
                                        draws=cfg.eval.draws)
                pictures["rgb"].append(to_uint8(rgb))
            if set(request.outputs) - {"rgb"}:
                alpha, depth, normal = render_geometry(s.means, s.normals, s.scales, s.opacities, V, K, path.width,
                                                       path.height, rc, seed=seed + i)
                if "alpha" in request.outputs:
                    pictures["alpha"].append(to_uint8(alpha.expand(-1, -1, -1, 3)))
                if "normal" in request.outputs:
                    pictures["normal"].append(normal_picture(normal, alpha))
                if "depth" in request.outputs:
                    depths.append((depth.cpu(), alpha.cpu()))
            bar.update(V.shape[0])
    if depths:
        pictures["depth"] = [depth_picture(torch.cat([d for d, _ in depths]), torch.cat([a for _, a in depths]))]
    written = []
    for o in request.outputs:
        name = f"{request.name}.mp4" if o == "rgb" else f"{request.name}_{o}.mp4"
        out = write_video(np.concatenate(pictures[o]), ctx.run_dir / name, fps)
        results.info("%s video (%s, %d frames, %dx%d, %g fps) written to %s", request.name, o, F, path.width,
                     path.height, fps, out)
        written.append(out)
    return written
