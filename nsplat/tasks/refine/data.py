"""The refine task's data: the frames to refine against and the initial scene (``data.source``: ``room`` or
``nerf``)."""
from __future__ import annotations

import dataclasses

import torch

from nsplat.cameras import perturb_viewmats
from nsplat.config import ConfigError
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.paths import resolve, resolve_data
from nsplat.data.room import load_room
from nsplat.data.views import PosedViews
from nsplat.scene import SurfelScene
from nsplat.tasks.refine.config import Config


def load_data(cfg: Config, device: torch.device) -> tuple[PosedViews, SurfelScene]:
    """Frames (initial ``viewmats``, ``viewmats_gt``, bool ``masks [B,H,W]``) and the initial scene of
    ``cfg.data`` (on ``device``)."""
    d = cfg.data
    if d.source == "room":
        room = load_room(d.room, resolve(d.cache_dir))
        frames = room.views()
        n = room.means.shape[0]
        scene = SurfelScene.from_points(cfg.scene, room.means, room.normals,
                                        scales=room.scales[:, None].expand(n, 2).contiguous(),
                                        opacities=torch.full((n,), d.init_opacity), features=room.colours)
    else:
        nf = d.nerf
        views = load_split(resolve_data(nf.root, "nerf_synthetic/lego_400"), nf.split, resolution=nf.resolution,
                           background=cfg.render.background if cfg.scene.channels == 3 else (1.0, 1.0, 1.0),
                           limit=nf.limit or None)
        if not nf.cloud:
            raise ConfigError("data.nerf.cloud: a PLY initial cloud is required for source 'nerf'")
        scene = SurfelScene.load_ply(resolve(nf.cloud), cfg.scene)
        extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
        g = torch.Generator().manual_seed(nf.perturb_seed)
        init = perturb_viewmats(views.viewmats, nf.rot_deg, nf.trans_frac * extent, generator=g)
        masks = torch.ones(views.images.shape[:3], dtype=torch.bool)
        frames = dataclasses.replace(views, masks=masks, viewmats=init.float(), viewmats_gt=views.viewmats)
    return frames.to(device), scene.to(device)
