"""Building a :class:`~nsplat.viewer.model.ViewModel` from a run folder or from a live training state.

:func:`load_run` reads a run folder (its ``config.yaml`` and latest checkpoint) for any task; the
``*_view`` builders wrap in-memory training state (called by the training loops' live-view hook).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import torch

from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.engine import op_seed
from nsplat.render import RenderConfig, background_of
from nsplat.runctx import RunContext
from nsplat.scene import SurfelScene
from nsplat.viewer.model import TrainingCameras, ViewModel


class RunError(ValueError):
    """The run folder cannot be viewed or exported (missing, no config, no checkpoint)."""


def read_run_config(run_dir: Path) -> tuple[str, Any]:
    """``(task name, resolved config)`` of a run folder; raises :class:`RunError` when unusable."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"--run {run_dir}: no such run folder")
    if not (run_dir / "config.yaml").is_file():
        raise RunError(f"--run {run_dir}: not a run folder (no config.yaml)")
    from nsplat.tasks import get_task

    raw = read_yaml(run_dir / "config.yaml")
    if "task" not in raw:
        raise RunError(f"--run {run_dir}: config.yaml has no 'task' key")
    try:
        task = get_task(raw["task"])
        return raw["task"], load_config(task.Config, raw, [])
    except ConfigError as exc:
        raise RunError(f"--run {run_dir}: {exc}") from exc


def _eval_unet(model: torch.nn.Module, residual: bool) -> Callable[[torch.Tensor], torch.Tensor]:
    """The U-Net of ``model`` as an eval-mode shader (restores the previous mode afterwards)."""

    def shade(cond: torch.Tensor) -> torch.Tensor:
        was = model.training
        model.eval()
        try:
            return model.unet(cond, base=cond[:, :3] if residual else None)
        finally:
            model.train(was)

    return shade


def neural_view(model: torch.nn.Module, cameras: TrainingCameras | None, seed: int = 0) -> ViewModel:
    """View of a :class:`nsplat.tasks.neural.NeuralRenderer` (features → op → U-Net)."""
    s, rc = model.scene, model.render_cfg
    return ViewModel(s.means, s.normals, s.scales, s.opacities, s.features, model.background,
                     shader=_eval_unet(model, model.residual), alpha_input=model.alpha_input, render_cfg=rc,
                     cameras=cameras, task="neural", seed=seed)


def _lambert(features: torch.Tensor, normals: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    from nsplat.shading import lambert

    return lambert(features, normals, viewmat)


def surfel_view(scene: SurfelScene, cameras: TrainingCameras | None, *, shading: str = "none",
                background: torch.Tensor | None = None, render_cfg: RenderConfig | None = None, task: str = "",
                seed: int = 0) -> ViewModel:
    """View of RGB surfels; ``shading="lambert"`` shades them with the paper's camera-relative lights."""
    bg = background if background is not None else scene.means.new_zeros(scene.features.shape[1])
    return ViewModel(scene.means, scene.normals, scene.scales, scene.opacities, scene.features, bg,
                     colours=_lambert if shading == "lambert" else None,
                     render_cfg=render_cfg or RenderConfig(), cameras=cameras, task=task, seed=seed)


def refine_view(model: torch.nn.Module, seed: int = 0) -> ViewModel:
    """View of a :class:`nsplat.tasks.refine.Refiner` (its shading, refined cameras as frusta)."""
    fr, s, rc = model.frames, model.scene, model.cfg.render
    with torch.no_grad():
        V, K = model.camera(torch.arange(len(fr), device=fr.images.device))
    cams = TrainingCameras(V.detach(), K.detach(), fr.width, fr.height, fr.images)
    bg = background_of(rc, s.features.shape[1], s.means)
    return ViewModel(s.means, s.normals, s.scales, s.opacities, s.features,
                     s.means.new_zeros(s.features.shape[1]) if bg is None else bg,
                     colours=lambda f, n, v: model.colours(v), render_cfg=rc, cameras=cams, task="refine", seed=seed)


# ---------------------------------------------------------------------------------------------- run folders
def _require_checkpoint(run_dir: Path) -> None:
    if not (run_dir / "checkpoints" / "latest").is_file():
        raise RunError(f"--run {run_dir}: no checkpoint yet (train first, or wait for the first checkpoint)")


def load_run(run_dir: Path, device: torch.device | str = "cpu") -> ViewModel:
    """The trained scene of ``run_dir`` (any task) as a :class:`ViewModel` on ``device``."""
    run_dir = Path(run_dir)
    task, cfg = read_run_config(run_dir)
    device = torch.device(device)
    ctx = RunContext(run_dir=run_dir, device=device, seed=int(getattr(cfg, "seed", 0)), resume=True)
    if task == "demo":
        return _demo(cfg, device)
    _require_checkpoint(run_dir)
    if task == "neural":
        from nsplat.tasks import neural

        model = neural.load_model(cfg, ctx).eval()
        train = neural.load_views(cfg, "train", device)
        cams = TrainingCameras(train.viewmats, train.Ks, train.width, train.height, train.images)
        return neural_view(model, cams, seed=neural.eval_seed(cfg))
    if task == "reconstruct":
        return _reconstruct(cfg, ctx)
    if task == "refine":
        from nsplat.tasks import refine

        model, _ = refine.restore(cfg, ctx)
        return refine_view(model.eval(), seed=op_seed(ctx.seed, "eval"))
    raise RunError(f"--run {run_dir}: task {task!r} has no viewer")


def _demo(cfg: Any, device: torch.device) -> ViewModel:
    from nsplat.tasks.demo import demo_scene, orbit_cameras

    sc = {k: v.to(device) for k, v in demo_scene(cfg.points, cfg.seed).items()}
    V, K = orbit_cameras(cfg.views, cfg.resolution)
    cams = TrainingCameras(V.to(device), K.to(device), cfg.resolution, cfg.resolution)
    return ViewModel(sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"],
                     torch.ones(3, device=device), cameras=cams, task="demo", seed=cfg.seed)


def _reconstruct(cfg: Any, ctx: RunContext) -> ViewModel:
    from nsplat.data.dss import cache_file, view_cameras
    from nsplat.data.pointclouds import load_dss_shape
    from nsplat.tasks import reconstruct as rec

    pc = load_dss_shape(cfg.data.shape, cfg.data.root or None)
    scene = rec.restore(cfg, ctx)
    V, K = view_cameras(cfg.data.views, pc, cfg.data)
    cache = cache_file(cfg.data, cfg.render, "train")
    images = None
    if cache.is_file():  # GT images only if already rendered (never re-render them for viewing)
        have = torch.load(cache, weights_only=True)
        images = have[:cfg.data.views] if have.shape[0] >= cfg.data.views else None
    cams = TrainingCameras(V.to(ctx.device), K.to(ctx.device), cfg.data.width, cfg.data.height,
                           None if images is None else images.to(ctx.device))
    return surfel_view(scene, cams, shading=cfg.optim.shading, render_cfg=cfg.render, task="reconstruct",
                       seed=op_seed(ctx.seed, "eval"))


def cameras_of(images: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> TrainingCameras:
    """Training cameras from ``images [V,H,W,C]``, ``viewmats [V,4,4]``, ``Ks [V,3,3]``."""
    V, H, W = images.shape[:3]
    return TrainingCameras(viewmats, Ks, int(W), int(H), images[..., :3] if images.shape[-1] >= 3 else None)

