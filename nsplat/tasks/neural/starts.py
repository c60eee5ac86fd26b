"""The starts of the neural task's stage 1 (``geometry.init``, :func:`~nsplat.tasks.neural.capture.start_kind`):
the visual hull of the training silhouettes, the SfM points of a COLMAP capture (or of the model beside a
``transforms.json``), the points triangulated from a ``transforms.json`` folder's photos, a PLY of this project, of
3D Gaussian splatting or of a scanner, the point cloud a ``transforms.json`` names, or random points in the bounding
box or the cameras' common view, plus, for unmasked photos, the background sphere of
:mod:`~nsplat.tasks.neural.background` (:func:`initial_geometry`); and the stage-1 scene's config
(:func:`geometry_scene_config`). A start most training views cannot see is refused
(:func:`nsplat.tasks.neural.diagnosis.check_seen`)."""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import torch
from plyfile import PlyData

from nsplat.cameras import camera_centres
from nsplat.config import ConfigError
from nsplat.data.paths import resolve
from nsplat.data.pointclouds import PlainCloud, check_ply_header, read_point_ply
from nsplat.data.views import PosedViews
from nsplat.data.visual_hull import hull_points, silhouette_box
from nsplat.errors import DataError
from nsplat.gaussians.kernel import surfels_of_gaussians
from nsplat.gaussians.ply import is_gaussian_ply, read_gaussian_ply
from nsplat.scene import SceneConfig, SurfelScene, knn_spacing
from nsplat.tasks.neural.background import sphere_background
from nsplat.tasks.neural.capture import background_sphere, prepare, scene_points, start_kind
from nsplat.tasks.neural.config import FRAME_BOX, Config
from nsplat.tasks.neural.diagnosis import check_seen
from nsplat.tasks.neural.sfm_init import fill_box, fill_points, plane_normals, sfm_surfels

log = logging.getLogger(__name__)


def geometry_scene_config(cfg: Config) -> SceneConfig:
    """Stage-1 scene: RGB colour (sigmoid), or view-dependent RGB (spherical harmonics, stored as is),
    and the stage's learnable attributes."""
    g = cfg.geometry
    return SceneConfig(channels=g.channels(), learn=list(g.learn), opacity=g.opacity, scale=None,
                       feature_activation="identity" if g.optim.shading == "sh" else "sigmoid")


def initial_geometry(cfg: Config, train: PosedViews, seed: int) -> SurfelScene:
    """Stage 1's initial surfels (``geometry.init``, :func:`start_kind`): the visual hull's surface voxels, the
    filtered SfM or triangulated points (:func:`~nsplat.tasks.neural.sfm_init.sfm_surfels`), a PLY, a capture's
    point cloud, or random points in the box or in the cameras' common view; with
    ``geometry.background.model: sphere`` the background surfels are appended. Opacities start at
    ``geometry.init_opacity``, the random fills' (SfM and common view) at ``geometry.sfm.fill_opacity``."""
    g = cfg.geometry
    scfg = geometry_scene_config(cfg)
    device = train.images.device
    kind = start_kind(cfg)
    if kind == "ply":
        return _ply_scene(cfg, resolve(g.ply or ""), train, device, seed)
    spacing = None
    if kind in ("sfm", "triangulated"):
        means, normals, colours, spacing = _sfm_points(cfg, train, seed)
    elif kind == "random":
        means, normals, colours = _random_points(scene_box(cfg, train, kind), g.max_points, seed)
    elif kind == "capture_ply":
        means, normals, colours = _capture_cloud(cfg, seed)
    elif kind == "view_fill":
        box = scene_box(cfg, train, kind)
        lo, hi = torch.tensor(box[:3], dtype=torch.float64), torch.tensor(box[3:], dtype=torch.float64)
        try:
            means, normals, colours = fill_points(lo, hi, train.to("cpu"), g.max_points, g.sfm.fill_seen,
                                                  torch.Generator().manual_seed(seed))
        except ValueError as exc:
            raise ConfigError(f"geometry.init: auto: {exc}") from exc
        log.info("common-view start: %d random points in the box %s seen by %.0f%% of the training views%s",
                 g.max_points, [round(v, 4) for v in box], 100 * g.sfm.fill_seen,
                 f" ({prepare(cfg).note})" if cfg.data.is_capture() and prepare(cfg).note else "")
    else:
        box = scene_box(cfg, train, kind)
        try:
            hp = hull_points(train.to("cpu"), box, g.grid, alpha_threshold=g.alpha_threshold, dilate=g.dilate,
                             min_seen=g.min_seen, max_points=g.max_points, seed=seed)
        except ValueError as exc:  # an empty hull: a box that misses the scene
            raise ConfigError(f"geometry.bbox: {[round(v, 3) for v in box]}: {exc} (null takes the scene's box from "
                              f"the training silhouettes)") from exc
        log.info("visual hull: %d surface points (voxel %.4f)", hp.means.shape[0], hp.voxel)
        means, normals, colours = hp.means, hp.normals, hp.colours
    check_seen(cfg, means, train.to("cpu"), kind)
    scales = None
    opacities = torch.full((means.shape[0],), g.init_opacity)
    if kind in ("sfm", "triangulated") and g.sfm.fill > 0:     # the fill rows end the SfM part
        opacities[means.shape[0] - g.sfm.fill:] = g.sfm.fill_opacity
    if kind == "view_fill":
        opacities[:] = g.sfm.fill_opacity
    if g.background.model == "sphere":
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


def _ply_scene(cfg: Config, path: Path, train: PosedViews, device: torch.device, seed: int) -> SurfelScene:
    """Stage 1's surfels from the PLY at ``path``, in whichever layout it has:

    * this project's own (``f_0 …``: a run's ``geometry.ply``, :meth:`SurfelScene.save_ply`): read as stored;
    * 3D Gaussian splatting's (``f_dc_0 …``, :mod:`nsplat.gaussians.ply`; e.g. ``export --format 3dgs``):
      positions, normals, tangent std-devs, opacities and the colour up to ``geometry.sh_degree`` (the mean
      colour without view dependence when ``geometry.optim.shading`` is ``none``); opacities and std-devs
      converted from 3DGS's kernel to nsplat's over the training cameras ``train`` with ``render.lowpass``
      (:func:`nsplat.gaussians.kernel.surfels_of_gaussians`, the inverse of the export's conversion; an
      antialiased file's header comments fold its per-view compensation in);
    * any other point cloud with ``x y z`` (a scanner's): its normals or, without them, plane fits of the
      ``geometry.sfm.k`` nearest neighbours; its colours or grey; std-devs from the point spacing
      (``geometry.scale_factor``), opacity ``geometry.init_opacity``.

    Of a 3DGS file or a plain cloud, at most ``geometry.max_points`` points are kept (a random subset drawn
    with ``seed``).
    """
    g, scfg = cfg.geometry, geometry_scene_config(cfg)
    if not path.is_file():
        raise FileNotFoundError(f"geometry.ply: no PLY file at {path}")
    check_ply_header(path)
    try:
        names = set(PlyData.read(str(path))["vertex"].data.dtype.names)
    except Exception as exc:  # noqa: BLE001 - plyfile's parse errors do not name the file
        raise DataError(f"{path}: not a readable PLY file with a 'vertex' element: {exc}") from exc
    if "f_0" in names and not is_gaussian_ply(names):
        return SurfelScene.load_ply(path, scfg, device=device)
    gen = torch.Generator().manual_seed(seed)
    if is_gaussian_ply(names):
        gs = read_gaussian_ply(path)
        keep = _subset(gs["means"].shape[0], g.max_points, gen)
        channels = scfg.channels  # RGB, or SH up to geometry.sh_degree: truncate or pad the file's bands
        features = torch.zeros(len(keep), channels, dtype=torch.float64)
        features[:, :min(channels, gs["features"].shape[1])] = gs["features"][keep][:, :channels]
        if g.optim.shading == "none":
            features = features.clamp(0.0, 1.0)
        log.info("3DGS PLY: %d of %d Gaussians as surfels (file SH degree %d, %d colour channels, %s)", len(keep),
                 gs["means"].shape[0], gs["degree"], channels, "antialiased" if gs["antialiased"] else "classic")
        means, normals = gs["means"][keep], gs["normals"][keep]
        scales, opacities = surfels_of_gaussians(means, normals, gs["scales"][keep], gs["opacities"][keep],
                                                 train.viewmats.cpu(), train.Ks.cpu(), train.width, train.height,
                                                 lowpass=cfg.render.lowpass, near=cfg.render.near, far=cfg.render.far,
                                                 antialiased=bool(gs["antialiased"]))
        rows = {k: v.float().to(device) for k, v in
                (("means", means), ("normals", normals), ("scales", scales), ("opacities", opacities))}
        return SurfelScene.from_points(scfg, rows["means"], rows["normals"], scales=rows["scales"].clamp_min(1e-9),
                                       opacities=rows["opacities"] if g.opacity is None else None,
                                       features=features.float().to(device))
    means, normals, colours = _cloud_points(cfg, read_point_ply(path), gen, path)
    features = torch.cat([colours, colours.new_zeros(colours.shape[0], scfg.channels - 3)], 1)
    return SurfelScene.from_points(scfg, means.to(device), normals.to(device),
                                   opacities=torch.full((means.shape[0],), g.init_opacity, device=device)
                                   if g.opacity is None else None,
                                   features=features.to(device), scale_factor=g.scale_factor)


def _cloud_points(cfg: Config, cloud: PlainCloud, gen: torch.Generator, where: Path) -> tuple[torch.Tensor, ...]:
    """``(means, normals, colours)`` float32 of at most ``geometry.max_points`` points of ``cloud`` (read from
    ``where``; a random subset drawn with ``gen``): its normals or plane fits of the ``geometry.sfm.k``
    nearest neighbours, its colours (clamped to [0.02, 0.98]) or grey."""
    g = cfg.geometry
    keep = _subset(cloud.points.shape[0], g.max_points, gen)
    means = cloud.points[keep].float()
    if cloud.normals is None and len(keep) < 3:
        raise DataError(f"{where}: a point cloud without normals needs at least 3 points for plane fits, "
                        f"got {len(keep)}")
    normals = (torch.from_numpy(plane_normals(means.double().numpy(), min(g.sfm.k, len(keep) - 1))).float()
               if cloud.normals is None else cloud.normals[keep].float())
    colours = torch.full_like(means, 0.5) if cloud.colours is None else cloud.colours[keep].float()
    log.info("point cloud: %d of %d points (normals %s, colours %s)", len(keep), cloud.points.shape[0],
             "from the file" if cloud.normals is not None else "from plane fits",
             "from the file" if cloud.colours is not None else "grey")
    return means, normals, colours.clamp(0.02, 0.98)


def _capture_cloud(cfg: Config, seed: int) -> tuple[torch.Tensor, ...]:
    """``(means, normals, colours)`` of the point cloud the capture's ``transforms.json`` names
    (``ply_file_path``, in the file's world), moved into the training frame (:func:`_cloud_points`)."""
    prep = prepare(cfg)
    cloud = read_point_ply(prep.ply)
    cloud = dataclasses.replace(cloud, points=prep.to_training(cloud.points))
    log.info("start: the point cloud of %s", prep.ply)
    return _cloud_points(cfg, cloud, torch.Generator().manual_seed(seed), prep.ply)


def _subset(count: int, limit: int, gen: torch.Generator) -> torch.Tensor:
    """All of ``count`` rows, or a sorted random subset of ``limit`` of them."""
    if count <= limit:
        return torch.arange(count)
    return torch.randperm(count, generator=gen)[:limit].sort().values


def _sfm_points(cfg: Config, train: PosedViews, seed: int) -> tuple[torch.Tensor, ...]:
    """``(means, normals, colours, spacing)`` of the capture's filtered SfM points (``geometry.sfm``), at most
    ``geometry.max_points`` of them (a random subset drawn with ``seed``). With a background sphere and
    ``geometry.sfm.background_points: false`` only the scene's points are used
    (:func:`nsplat.tasks.neural.capture.scene_points`; all of them when fewer than ``2·geometry.sfm.k``
    lie in the scene): the distant ones are the background, which the sphere models."""
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
        sf = sfm_surfels(points, camera_centres(train.viewmats.cpu().double()), min_track=s.min_track,
                         max_error=s.max_error,
                         k=s.k, std_ratio=s.std_ratio)
    except ValueError as exc:
        raise ConfigError(f"geometry.sfm: {exc}") from exc
    log.info("SfM init: %d of %d %s points kept", sf.means.shape[0], len(points),
             "triangulated" if prepare(cfg).origin == "triangulated" else "SfM")
    keep = torch.arange(sf.means.shape[0])
    gen = torch.Generator().manual_seed(seed)
    if keep.numel() > cfg.geometry.max_points:
        keep = torch.randperm(keep.numel(), generator=gen)[:cfg.geometry.max_points].sort().values
    out = sf.means[keep], sf.normals[keep], sf.colours[keep], sf.spacing[keep]
    return _with_fill(cfg, train, out, gen) if s.fill > 0 else out


def _with_fill(cfg: Config, train: PosedViews, sfm: tuple[torch.Tensor, ...], gen: torch.Generator
               ) -> tuple[torch.Tensor, ...]:
    """The SfM surfels ``sfm`` = ``(means [N,3], normals [N,3], colours [N,3], spacing [N])`` followed by
    ``geometry.sfm.fill`` random points (:func:`nsplat.tasks.neural.sfm_init.fill_points`) in the configured box; the
    new points' spacing is their 3-NN spacing among all ``N + fill`` points."""
    s = cfg.geometry.sfm
    if s.fill_box == "points":
        lo, hi = fill_box(sfm[0], s.fill_margin)
    else:
        box = scene_box(cfg, train, "sfm")
        lo, hi = torch.tensor(box[:3], dtype=torch.float64), torch.tensor(box[3:], dtype=torch.float64)
    try:
        means, normals, colours = fill_points(lo, hi, train.to("cpu"), s.fill, s.fill_seen, gen)
    except ValueError as exc:
        raise ConfigError(f"geometry.sfm.fill: {exc}") from exc
    all_means = torch.cat([sfm[0], means])
    spacing = torch.from_numpy(knn_spacing(all_means)[len(sfm[0]):]).float()
    log.info("SfM init: %d random points added in the box %s..%s", s.fill, lo.tolist(), hi.tolist())
    return all_means, torch.cat([sfm[1], normals]), torch.cat([sfm[2], colours]), torch.cat([sfm[3], spacing])


def scene_box(cfg: Config, train: PosedViews, kind: str) -> tuple[float, ...]:
    """The scene's box for the start ``kind``: ``geometry.bbox`` when set; else, for the hull, the box around the
    training silhouettes' hull (:func:`~nsplat.data.visual_hull.silhouette_box`); else
    :data:`~nsplat.tasks.neural.config.FRAME_BOX`."""
    g = cfg.geometry
    if g.bbox is not None:
        return tuple(g.bbox)
    if kind != "hull":
        return FRAME_BOX
    try:
        box = silhouette_box(train.to("cpu"), alpha_threshold=g.alpha_threshold, dilate=g.dilate,
                             min_seen=g.min_seen)
    except ValueError as exc:
        raise ConfigError(f"geometry.bbox: null: {exc}") from exc
    log.info("the scene's box from the training silhouettes: %s", [round(v, 4) for v in box])
    return box


def _random_points(bbox: tuple[float, ...], count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` points uniform in ``bbox`` with uniformly random unit normals and grey colour (float32)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(bbox[:3]), torch.tensor(bbox[3:])
    means = lo + (hi - lo) * torch.rand(count, 3, generator=g)
    normals = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    return means, normals, torch.full((count, 3), 0.5)
