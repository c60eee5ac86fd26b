"""Stage 1's initial surfels for task ``neural``: the scene config, and the points (visual hull of the
training silhouettes, the SfM points of a COLMAP capture, a PLY, or random points in the bounding box),
plus, for unmasked photos, the background sphere (:mod:`nsplat.background`)."""
from __future__ import annotations

import logging

import torch

from nsplat.config import ConfigError
from nsplat.data.paths import resolve
from nsplat.data.views import PosedViews
from nsplat.data.visual_hull import hull_points
from nsplat.scene import SceneConfig, SurfelScene, knn_spacing
from nsplat.tasks.neural_config import Config

log = logging.getLogger(__name__)


def geometry_scene_config(cfg: Config) -> SceneConfig:
    """Stage-1 scene: RGB colour (sigmoid), or view-dependent RGB (spherical harmonics, stored as is),
    and the stage's learnable attributes."""
    g = cfg.geometry
    return SceneConfig(channels=g.channels(), learn=list(g.learn), opacity=g.opacity, scale=None,
                       feature_activation="identity" if g.optim.shading == "sh" else "sigmoid")


def initial_geometry(cfg: Config, train: PosedViews, seed: int) -> SurfelScene:
    """Stage 1's initial surfels (``geometry.init``): the visual hull's surface voxels, the filtered SfM
    points, a PLY, or random points in the box; with ``geometry.background.model: sphere`` the background surfels are appended.
    Opacities start at ``geometry.init_opacity``, the SfM fill's at ``geometry.sfm.fill_opacity``."""
    g = cfg.geometry
    scfg = geometry_scene_config(cfg)
    device = train.images.device
    if g.init == "ply":
        return SurfelScene.load_ply(resolve(g.ply or ""), scfg, device=device)
    spacing = None
    if g.init == "sfm":
        means, normals, colours, spacing = _sfm_points(cfg, train, seed)
    elif g.init == "random":
        means, normals, colours = _random_points(g.bbox, g.max_points, seed)
    else:
        hp = hull_points(train.to("cpu"), tuple(g.bbox), g.grid, alpha_threshold=g.alpha_threshold,
                         dilate=g.dilate, min_seen=g.min_seen, max_points=g.max_points, seed=seed)
        log.info("visual hull: %d surface points (voxel %.4f)", hp.means.shape[0], hp.voxel)
        means, normals, colours = hp.means, hp.normals, hp.colours
    scales = None
    opacities = torch.full((means.shape[0],), g.init_opacity)
    if g.init == "sfm" and g.sfm.fill > 0:                      # the fill rows end the SfM part
        opacities[means.shape[0] - g.sfm.fill:] = g.sfm.fill_opacity
    if g.background.model == "sphere":
        from nsplat.background import sphere_background
        from nsplat.tasks.neural_capture import background_sphere

        centre, radius = background_sphere(cfg)
        bg = sphere_background(train.to("cpu"), centre, radius, g.background.points)
        log.info("background sphere: %d points, radius %.3f", bg[0].shape[0], radius)
        if spacing is None:
            spacing = torch.from_numpy(knn_spacing(means)).float()
        scales = torch.cat([g.scale_factor * spacing, bg[3]])
        means, normals, colours = (torch.cat([a.float(), b]) for a, b in zip((means, normals, colours), bg[:3]))
        opacities = torch.cat([opacities, torch.full((bg[0].shape[0],), g.init_opacity)])
    elif spacing is not None:
        scales = g.scale_factor * spacing
    means, normals = means.to(device), normals.to(device)
    colours = colours.clamp(0.02, 0.98).to(device)
    features = torch.cat([colours, colours.new_zeros(colours.shape[0], scfg.channels - 3)], 1)  # SH: view-independent
    return SurfelScene.from_points(scfg, means, normals, scales=None if scales is None else scales.to(device),
                                   opacities=opacities.to(device) if g.opacity is None else None,
                                   features=features, scale_factor=g.scale_factor)


def _sfm_points(cfg: Config, train: PosedViews, seed: int) -> tuple[torch.Tensor, ...]:
    """``(means, normals, colours, spacing)`` of the capture's filtered SfM points (``geometry.sfm``), at most
    ``geometry.max_points`` of them (a random subset drawn with ``seed``). With a background sphere and
    ``geometry.sfm.background_points: false`` only the scene's points are used
    (:func:`nsplat.tasks.neural_capture.scene_points`; all of them when fewer than ``2·geometry.sfm.k``
    lie in the scene): the distant ones are the background, which the sphere models."""
    from nsplat.background import camera_centres
    from nsplat.sfm_init import sfm_surfels
    from nsplat.tasks.neural_capture import prepare, scene_points

    points = prepare(cfg).points
    if cfg.geometry.background.model == "sphere" and not cfg.geometry.sfm.background_points:
        near = scene_points(cfg)
        if near is not None and len(near) >= 2 * cfg.geometry.sfm.k:
            points = near
        else:
            log.warning("SfM init: only %d points near the scene centre; using all %d (background ones too)",
                        0 if near is None else len(near), 0 if points is None else len(points))
    if points is None or len(points) < 4:
        raise ConfigError(f"geometry.init: sfm needs SfM points; the model under {cfg.data.root} has "
                          f"{0 if points is None else len(points)}")
    s = cfg.geometry.sfm
    try:
        sf = sfm_surfels(points, camera_centres(train.viewmats.cpu()), min_track=s.min_track, max_error=s.max_error,
                         k=s.k, std_ratio=s.std_ratio)
    except ValueError as exc:
        raise ConfigError(f"geometry.sfm: {exc}") from exc
    log.info("SfM init: %d of %d points kept", sf.means.shape[0], len(points))
    keep = torch.arange(sf.means.shape[0])
    gen = torch.Generator().manual_seed(seed)
    if keep.numel() > cfg.geometry.max_points:
        keep = torch.randperm(keep.numel(), generator=gen)[:cfg.geometry.max_points].sort().values
    out = sf.means[keep], sf.normals[keep], sf.colours[keep], sf.spacing[keep]
    return _with_fill(cfg, train, out, gen) if s.fill > 0 else out


def _with_fill(cfg: Config, train: PosedViews, sfm: tuple[torch.Tensor, ...], gen: torch.Generator
               ) -> tuple[torch.Tensor, ...]:
    """The SfM surfels ``sfm`` = ``(means [N,3], normals [N,3], colours [N,3], spacing [N])`` followed by
    ``geometry.sfm.fill`` random points (:func:`nsplat.sfm_init.fill_points`) in the configured box; the
    new points' spacing is their 3-NN spacing among all ``N + fill`` points."""
    from nsplat.sfm_init import fill_box, fill_points

    s, g = cfg.geometry.sfm, cfg.geometry
    if s.fill_box == "points":
        lo, hi = fill_box(sfm[0], s.fill_margin)
    else:
        lo, hi = torch.tensor(g.bbox[:3], dtype=torch.float64), torch.tensor(g.bbox[3:], dtype=torch.float64)
    try:
        means, normals, colours = fill_points(lo, hi, train.to("cpu"), s.fill, s.fill_seen, gen)
    except ValueError as exc:
        raise ConfigError(f"geometry.sfm.fill: {exc}") from exc
    all_means = torch.cat([sfm[0], means])
    spacing = torch.from_numpy(knn_spacing(all_means)[len(sfm[0]):]).float()
    log.info("SfM init: %d random points added in the box %s..%s", s.fill, lo.tolist(), hi.tolist())
    return all_means, torch.cat([sfm[1], normals]), torch.cat([sfm[2], colours]), torch.cat([sfm[3], spacing])


def _random_points(bbox: tuple[float, ...], count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` points uniform in ``bbox`` with uniformly random unit normals and grey colour (float32)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(bbox[:3]), torch.tensor(bbox[3:])
    means = lo + (hi - lo) * torch.rand(count, 3, generator=g)
    normals = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    return means, normals, torch.full((count, 3), 0.5)
