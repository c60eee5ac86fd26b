"""Fitted surfels of a neural run, for the benchmarks that study them (``rate_floor``, ``back_faces``,
``large_surfel_cost``, ``step_phases``): load a run's ``geometry.ply`` with its config's views, score it on
val, fit it further."""
from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Callable

import torch

from nsplat.config import load_config, read_yaml
from nsplat.data.views import PosedViews
from nsplat.engine import LogConfig
from nsplat.fitting import FitConfig, fit
from nsplat.metrics_image import psnr
from nsplat.render import RenderConfig, render_views
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.geometry import geometry_scene_config


@dataclasses.dataclass
class Fitted:
    """A run's fitted surfels with its config and views.

    Attributes:
        cfg: the neural config. train, val: its views. load: a fresh copy of the surfels (``geometry.ply``).
    """

    cfg: Config
    train: PosedViews
    val: PosedViews
    load: Callable[[], SurfelScene]


def load_fitted(config: str | Path, ply: str | Path, splits: tuple[str, ...] = ("train", "val")) -> Fitted:
    """The surfels in ``ply`` (written by a run of ``config``) with the config's ``splits``."""
    cfg = load_config(Config, read_yaml(config), [])
    cpu = torch.device("cpu")
    views = {s: load_views(cfg, s, cpu) for s in splits}
    scene_cfg = geometry_scene_config(cfg)
    return Fitted(cfg, views.get("train"), views.get("val"), lambda: SurfelScene.load_ply(ply, scene_cfg, device=cpu))


def val_psnr(scene: SurfelScene, cfg: Config, val: PosedViews) -> float:
    """Mean PSNR of ``scene`` on every view of ``val`` (evaluation render settings and draws)."""
    with torch.no_grad():
        rgb = torch.cat([render_views(scene, val.viewmats[s:s + 4], val.Ks[s:s + 4], val.width, val.height,
                                      cfg.eval_render(), seed=1000 + s, shading=cfg.geometry.optim.shading,
                                      background=val.background, draws=cfg.eval.draws)
                         for s in range(0, len(val), 4)]).clamp(0, 1)
    return float(psnr(rgb, val.images).mean())


def continue_fit(scene: SurfelScene, train: PosedViews, fit_cfg: FitConfig, render_cfg: RenderConfig,
                 seed: int) -> tuple[dict[str, float], float, float]:
    """Fit ``scene`` further with ``fit_cfg`` (checkpoints discarded): the last step's scalars, wall and CPU s."""
    t0, c0 = time.perf_counter(), time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        out = fit(scene, train, fit_cfg, render_cfg, tmp, seed=seed, background=train.background,
                  log=LogConfig(checkpoint=10 ** 9, progress=False))
    return out, time.perf_counter() - t0, time.process_time() - c0
