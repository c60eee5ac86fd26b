"""Stage 1's initial surfels for task ``neural``: the scene config, and the points (visual hull of the
training silhouettes, a PLY, or random points in the bounding box; the hull optionally thinned or
shifted for the poor-start study of docs/results.md)."""
from __future__ import annotations

import logging
import math

import torch

from nsplat.data.paths import resolve
from nsplat.data.views import PosedViews
from nsplat.data.visual_hull import hull_points
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.tasks.neural_config import Config

log = logging.getLogger(__name__)


def geometry_scene_config(cfg: Config) -> SceneConfig:
    """Stage-1 scene: RGB colour (sigmoid), or view-dependent RGB (spherical harmonics, stored as is),
    and the stage's learnable attributes."""
    g = cfg.geometry
    return SceneConfig(channels=g.channels(), learn=list(g.learn), opacity=g.opacity, scale=None,
                       feature_activation="identity" if g.optim.shading == "sh" else "sigmoid")


def initial_geometry(cfg: Config, train: PosedViews, seed: int) -> SurfelScene:
    """Stage 1's initial surfels (``geometry.init``): the visual hull's surface voxels (optionally a random
    ``init_fraction`` of them, shifted by ``init_shift`` voxels), a PLY, or random points in the box."""
    g = cfg.geometry
    scfg = geometry_scene_config(cfg)
    device = train.images.device
    if g.init == "ply":
        return SurfelScene.load_ply(resolve(g.ply or ""), scfg, device=device)
    if g.init == "random":
        means, normals, colours = _random_points(g.bbox, g.max_points, seed)
    else:
        hp = hull_points(train.to("cpu"), tuple(g.bbox), g.grid, alpha_threshold=g.alpha_threshold,
                         dilate=g.dilate, min_seen=g.min_seen, max_points=g.max_points, seed=seed)
        log.info("visual hull: %d surface points (voxel %.4f)", hp.means.shape[0], hp.voxel)
        keep = torch.randperm(hp.means.shape[0], generator=torch.Generator().manual_seed(seed))
        keep = keep[:max(1, round(g.init_fraction * hp.means.shape[0]))].sort().values
        shift = g.init_shift * hp.voxel / math.sqrt(3.0)
        means, normals, colours = hp.means[keep] + shift, hp.normals[keep], hp.colours[keep]
    means, normals = means.to(device), normals.to(device)
    colours = colours.clamp(0.02, 0.98).to(device)
    features = torch.cat([colours, colours.new_zeros(colours.shape[0], scfg.channels - 3)], 1)  # SH: view-independent
    return SurfelScene.from_points(scfg, means, normals,
                                   opacities=g.init_opacity if g.opacity is None else None,
                                   features=features, scale_factor=g.scale_factor)


def _random_points(bbox: tuple[float, ...], count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` points uniform in ``bbox`` with uniformly random unit normals and grey colour (float32)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(bbox[:3]), torch.tensor(bbox[3:])
    means = lo + (hi - lo) * torch.rand(count, 3, generator=g)
    normals = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    return means, normals, torch.full((count, 3), 0.5)
