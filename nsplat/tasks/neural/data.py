"""The neural task's posed views: the embedded procedural scene, a NeRF-synthetic folder (``data.root``, by default
that of ``data.scene``: :mod:`nsplat.data.nerf_scenes`) or a capture (COLMAP or ``transforms.json``,
:mod:`nsplat.tasks.neural.capture`), one split at a time as :class:`~nsplat.data.views.PosedViews`."""
from __future__ import annotations

from pathlib import Path

import torch

from nsplat.config import ConfigError
from nsplat.data.nerf_scenes import SCENE_ROOT
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.paths import resolve
from nsplat.data.procedural import ProceduralSpec, ensure_scene
from nsplat.data.views import PosedViews
from nsplat.tasks.neural.capture import capture_views
from nsplat.tasks.neural.config import Config


def scene_root(cfg: Config) -> Path:
    """Folder of the NeRF-synthetic-format scene (the procedural one is generated on first use)."""
    d = cfg.data
    if d.source == "nerf_synthetic":
        root = resolve(d.root or "")
        if not (root / "transforms_train.json").is_file():
            if d.scene is not None and d.root == SCENE_ROOT.format(scene=d.scene):
                raise ConfigError(f"data.scene: {d.scene}: no transforms_train.json in {root}; fetch the scene with "
                                  f"`nsplat data fetch {d.scene} --resolution 400` (or set data.root)")
            raise ConfigError(f"data.root: no transforms_train.json in {root}")
        return root
    p = d.procedural
    spec = ProceduralSpec(seed=p.seed, resolution=p.resolution, views=tuple(p.views), objects=p.objects)
    return ensure_scene(spec, resolve(p.cache_dir))


def load_views(cfg: Config, split: str, device: torch.device) -> PosedViews:
    """One split of the configured scene on ``device`` (a capture: :mod:`nsplat.tasks.neural.capture`)."""
    if cfg.data.is_capture():
        return capture_views(cfg, split, device)
    limit = {"train": cfg.data.train_limit, "val": cfg.data.val_limit, "test": cfg.data.test_limit}[split]
    views = load_split(scene_root(cfg), split, resolution=cfg.data.resolution, background=cfg.data.background,
                       limit=limit)
    return views.to(device)
