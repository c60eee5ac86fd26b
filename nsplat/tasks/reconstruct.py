"""Task ``reconstruct``: shape reconstruction from images (paper §4, Tables 1–3).

Data: ground-truth posed views of a DSS point cloud (:mod:`nsplat.tasks.reconstruct_views`), with their coverage. Init
(``init.kind``): the surface of the training views' visual hull, or a Fibonacci sphere enclosing the object (the
paper's). Optimisation: the surfel fitter :func:`nsplat.fitting.fit` on the run engine. Outputs in the run folder:
``metrics.json`` (Hausdorff/Chamfer, both definitions, see :mod:`nsplat.evaluation.shape_metrics`; the held-out PSNR;
``fit_seconds`` /
``cpu_seconds`` of this process, ``train_seconds`` / ``train_cpu_seconds`` of the steps over every segment of a
resumed run),
``reconstruction.ply``, ``renders/*.png`` (GT | result).
Data-parallel under torchrun (the fitter's, docs/distributed.md); rank 0 writes the outputs.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import torch
from matplotlib.figure import Figure

from nsplat import fitting
from nsplat.config import ConfigError, require, require_fields
from nsplat.data.pointclouds import PointCloud, load_shape
from nsplat.data.views import PosedViews
from nsplat.data.visual_hull import hull_points
from nsplat.evaluation.image_metrics import psnr
from nsplat.evaluation.shape_metrics import bbox_diagonal, nn_distances, point_cloud_distances
from nsplat.fitting import FitConfig, fit
from nsplat.ops import splat_tiled
from nsplat.render.renderer import RenderConfig
from nsplat.render.shading import lambert
from nsplat.render.view_model import TrainingCameras, ViewModel, surfel_view
from nsplat.run import distributed
from nsplat.run.checkpoint import load_checkpoint
from nsplat.run.context import RunContext
from nsplat.run.engine import LogConfig, Trainables, checkpoint_rows, op_seed, write_json
from nsplat.run.report import results
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.tasks.reconstruct_views import DataConfig, cached_views, gt_views, view_cameras

#: Runs data-parallel under torchrun (the CLI refuses tasks without this flag).
DISTRIBUTED = True


INIT_KINDS = ("sphere", "hull")


@dataclasses.dataclass
class InitConfig:
    """Initial surfels.

    Attributes:
        kind: ``sphere`` (the paper's: a Fibonacci sphere about the object's centre) or ``hull`` (points on the
            surface of the visual hull carved by the training views' coverage, :func:`hull_init`).
        count: number of points (null = the GT point count). radius: sphere radius in units of the
            enclosing-sphere radius (``sphere``; ``hull``: the half-width of the carved cube). albedo: initial grey
            albedo. scale: initial std-dev in units of the points' mean 3-NN spacing.
        grid: ``hull``: voxels per side of the carved cube. alpha_threshold: ``hull``: coverage at which a pixel
            is inside the silhouette.
    """

    kind: str = "sphere"
    count: int | None = None
    radius: float = 1.1
    albedo: float = 0.5
    scale: float = 1.0
    grid: int = 64
    alpha_threshold: float = 0.5

    def __post_init__(self) -> None:
        require(self.kind in INIT_KINDS, "kind", f"one of {INIT_KINDS}", self.kind)
        require_fields(self, count=">=1", radius=">0", albedo="unit", scale=">0", grid=">=2")
        require(0 < self.alpha_threshold < 1, "alpha_threshold", "a value in (0, 1)", self.alpha_threshold)


@dataclasses.dataclass
class Config:
    """Task ``reconstruct``.

    Attributes:
        task: ``reconstruct``. seed: the run seed (batch order, repositioning draws, every op seed).
        data: the ground-truth views (:class:`nsplat.tasks.reconstruct_views.DataConfig`). init: :class:`InitConfig`.
        scene: which point attributes exist and are learned (:class:`nsplat.scene.SceneConfig`; RGB albedo).
        render: the render settings (:class:`nsplat.render.renderer.RenderConfig`). optim: the fitter
            (:class:`nsplat.fitting.FitConfig`; Lambert shading). log: the cadences, ``log.validate`` the steps
            between shape metrics (TensorBoard; :class:`nsplat.run.engine.LogConfig`).
        heldout: held-out views scored at the end (``heldout_psnr`` in ``metrics.json``: the image metric to
            select a recipe on, the GT cloud being the test). renders: the first this many of them written to PNG.
    """

    task: str = "reconstruct"
    seed: int = 0
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    init: InitConfig = dataclasses.field(default_factory=InitConfig)
    scene: SceneConfig = dataclasses.field(default_factory=SceneConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    optim: FitConfig = dataclasses.field(default_factory=FitConfig)
    log: LogConfig = dataclasses.field(default_factory=LogConfig)
    heldout: int = 12
    renders: int = 3

    def __post_init__(self) -> None:
        require(self.task == "reconstruct", "task", "'reconstruct'", self.task)
        require_fields(self, seed=">=0", heldout=">=1", renders=">=0")
        require(self.renders <= self.heldout, "renders", f"at most heldout ({self.heldout})", self.renders)
        if self.scene.channels != 3:
            raise ConfigError(f"scene.channels: the reconstruct task shades RGB albedo, expected 3, "
                              f"got {self.scene.channels}")
        if self.optim.shading != "lambert":
            raise ConfigError("optim.shading: the reconstruct task's images are Lambert-shaded; expected 'lambert'")


def fibonacci_sphere(count: int, centre: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(points [count,3], outward normals [count,3])`` evenly spread on a sphere."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    r = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    n = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)
    return (centre.double() + radius * n).float(), n.float()


def hull_init(views: PosedViews, count: int, centre: torch.Tensor, half_width: float, grid: int,
              alpha_threshold: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(points [count,3], outward normals [count,3])`` on the visual hull of ``views`` (their ``masks``).

    The cube ``centre ± half_width`` is carved into ``grid³`` voxels (:func:`nsplat.data.visual_hull.hull_points`,
    silhouettes not dilated); the points are the surface voxels' centres, a random subset when there are more than
    ``count``, each repeated voxel moved by a uniform offset in its tangent plane (within the voxel) when fewer.
    """
    c = centre.double()
    bbox = tuple((c - half_width).tolist() + (c + half_width).tolist())
    hp = hull_points(views.to("cpu"), bbox, grid, alpha_threshold=alpha_threshold, dilate=0, min_seen=0.5)
    gen = torch.Generator().manual_seed(seed)
    n = hp.means.shape[0]
    pick = torch.randperm(n, generator=gen)[:count]
    if count > n:
        pick = torch.cat([pick, torch.randint(n, (count - n,), generator=gen)])
    means, normals = hp.means[pick].double(), hp.normals[pick].double()
    offset = (torch.rand(count, 3, generator=gen, dtype=torch.float64) - 0.5) * hp.voxel
    offset[: min(n, count)] = 0.0
    offset -= (offset * normals).sum(-1, keepdim=True) * normals
    return (means + offset).float(), normals.float()


def init_scene(pc: PointCloud, cfg: Config, views: PosedViews | None = None, seed: int = 0) -> SurfelScene:
    """The initial scene: ``init.count`` points on a sphere of radius ``init.radius ×`` the enclosing radius
    (``init.kind: sphere``) or on the visual hull of ``views`` (``hull``; :func:`hull_init`)."""
    count = cfg.init.count if cfg.init.count is not None else pc.points.shape[0]
    if count < 4:
        raise ConfigError(f"init.count: expected >= 4, got {count}")
    if cfg.init.kind == "hull":
        if views is None or views.masks is None:
            raise ConfigError("init.kind: 'hull' needs training views with coverage masks")
        means, normals = hull_init(views, count, pc.center, cfg.init.radius * pc.radius, cfg.init.grid,
                                   cfg.init.alpha_threshold, seed)
    else:
        means, normals = fibonacci_sphere(count, pc.center, cfg.init.radius * pc.radius)
    return SurfelScene.from_points(cfg.scene, means, normals, features=cfg.init.albedo, scale_factor=cfg.init.scale)


# ---------------------------------------------------------------------------------------------- run
def build(cfg: Config, device: torch.device | str, points: int) -> Trainables:
    """The task contract's ``build``: the fitter's module ``scene`` (``points`` surfels) and its optimiser."""
    return fitting.build(SurfelScene(cfg.scene, points, device=device), cfg.optim)


def run(cfg: Config, ctx: RunContext) -> dict[str, float]:
    """Reconstruct ``cfg.data.shape``; writes ``metrics.json``, ``reconstruction.ply`` and PNG renders."""
    torch.manual_seed(ctx.seed)
    t0, c0 = time.time(), time.process_time()
    pc = load_shape(cfg.data.shape, cfg.data.root or None)
    views = gt_views(pc, cfg.data, cfg.render, cfg.data.views).to(ctx.device)
    scene = init_scene(pc, cfg, views, seed=ctx.seed).to(ctx.device)
    init_metrics = point_cloud_distances(scene.means, pc.points)

    def validate(done: int, writer: Any) -> dict[str, float]:
        m = point_cloud_distances(scene.means, pc.points)  # chamfer first: the progress bar shows it
        return {f"shape/{k}": m[k] for k in ("chamfer", "hausdorff", "chamfer_sq", "hausdorff_sq")}

    scalars = fit(scene, views, cfg.optim, cfg.render, ctx.run_dir, log=cfg.log, seed=ctx.seed, resume=ctx.resume,
                  validate=validate, desc="reconstruct")
    if not distributed.is_main():  # under torchrun rank 0 writes the outputs
        return {}
    metrics = _finish(cfg, ctx, pc, scene)
    metrics.update(init={k: v for k, v in init_metrics.items()}, final_loss=scalars.get("train/loss"),
                   fit_seconds=time.time() - t0, cpu_seconds=time.process_time() - c0,
                   train_seconds=scalars["time/train_s"], train_cpu_seconds=scalars["time/train_cpu_s"],
                   train_cpu_since_step=scalars["time/cpu_since"])
    write_json(ctx.run_dir / "metrics.json", metrics)
    results.info("chamfer %.3e (sq %.3e)  hausdorff %.3e (sq %.3e)  held-out PSNR %.2f dB", metrics["chamfer"],
                 metrics["chamfer_sq"], metrics["hausdorff"], metrics["hausdorff_sq"], metrics["heldout_psnr"])
    return metrics


def _finish(cfg: Config, ctx: RunContext, pc: PointCloud, scene: SurfelScene) -> dict:
    scene.save_ply(ctx.run_dir / "reconstruction.ply")
    held, rec = render_heldout(cfg, pc, scene)
    write_renders(cfg, ctx, pc, scene, held, rec)
    m = point_cloud_distances(scene.means.detach().cpu(), pc.points)
    m["heldout_psnr"] = float(psnr(rec.clamp(0, 1), held.images).mean())
    return {"shape": cfg.data.shape, "renderer": cfg.render.renderer, "estimator": cfg.render.estimator,
            "samples": cfg.render.samples, "views": cfg.data.views, "epochs": cfg.optim.epochs,
            "resolution": [cfg.data.width, cfg.data.height], "points": scene.num_points, "seed": ctx.seed, **m}


def restore(cfg: Config, ctx: RunContext) -> SurfelScene:
    """The scene of the run's latest checkpoint (on ``ctx.device``)."""
    payload = load_checkpoint(ctx.run_dir, map_location="cpu")
    t = build(cfg, "cpu", checkpoint_rows(payload, "scene", "_means"))
    t.load(payload)
    return t.modules["scene"].to(ctx.device)


def render_heldout(cfg: Config, pc: PointCloud, scene: SurfelScene) -> tuple[PosedViews, torch.Tensor]:
    """The ``cfg.heldout`` held-out GT views and the scene's images of them ``[B,H,W,3]`` (CPU), rendered as the GT
    is: :func:`nsplat.ops.splat_tiled` at ``data.gt_tol`` (the dense oracle's image to that tolerance)."""
    held = gt_views(pc, cfg.data, cfg.render, cfg.heldout, heldout=True)
    with torch.no_grad():
        means, normals, scales, opacities, features = (t.detach().cpu() for t in (
            scene.means, scene.normals, scene.scales, scene.opacities, scene.features))
        shaded = lambert(features, normals, held.viewmats)
        rec = splat_tiled(means, normals, scales, opacities, shaded, held.viewmats, held.Ks, cfg.data.width,
                          cfg.data.height, tol=cfg.data.gt_tol, near=cfg.render.near, far=cfg.render.far,
                          lowpass=cfg.render.lowpass, backface_cull=cfg.render.backface_cull).image
    return held, rec


def write_renders(cfg: Config, ctx: RunContext, pc: PointCloud, scene: SurfelScene,
                  held: PosedViews | None = None, rec: torch.Tensor | None = None) -> list[Path]:
    """PNGs ``renders/view_<i>.png`` of the first ``cfg.renders`` held-out views: GT | reconstruction
    (:func:`render_heldout`, unless given); and ``renders/points.png``, a scatter plot of both clouds."""
    if cfg.renders < 1:
        return []
    if held is None or rec is None:
        held, rec = render_heldout(cfg, pc, scene)
    folder = ctx.run_dir / "renders"
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for b in range(cfg.renders):
        pair = torch.cat([held.images[b], rec[b]], 1).clamp(0, 1)
        p = folder / f"view_{b}.png"
        iio.imwrite(p, (pair.numpy() * 255).round().astype(np.uint8))
        paths.append(p)
    paths.append(write_point_plot(folder / "points.png", scene.means.detach().cpu(), pc))
    return paths


def write_point_plot(path: Path, points: torch.Tensor, pc: PointCloud) -> Path:
    """Scatter plot ``path`` of the GT cloud and ``points [N,3]`` (coloured by distance to the GT, in units
    of the GT bounding-box diagonal, clipped at 0.1), from two directions."""
    gt = pc.points.double().numpy()
    pred = points.double().numpy()
    dist = nn_distances(pred, gt) / bbox_diagonal(gt)
    fig = Figure(figsize=(7, 6))
    lo, hi = gt.min(0), gt.max(0)
    pad = 0.25 * (hi - lo)
    for i, (elev, azim) in enumerate(((20, -60), (20, 120))):
        for j, (pts, col, title) in enumerate(((gt, "0.4", "ground truth"), (pred, dist, "reconstruction"))):
            ax = fig.add_subplot(2, 2, 1 + 2 * i + j, projection="3d")
            if isinstance(col, str):
                ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=0.3, color=col)
            else:
                sc = ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=0.3, c=col, cmap="viridis", vmin=0.0, vmax=0.1)
            ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
            ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
            ax.set_zlim(lo[2] - pad[2], hi[2] + pad[2])
            ax.view_init(elev=elev, azim=azim)
            ax.set_axis_off()
            if i == 0:
                ax.set_title(title, fontsize=8)
    fig.subplots_adjust(left=0.0, right=0.85, bottom=0.0, top=0.95, wspace=0.0, hspace=0.0)
    fig.colorbar(sc, ax=fig.axes, shrink=0.5, label="distance to GT / diagonal")
    fig.savefig(path, dpi=110)
    return path


def evaluate(cfg: Config, ctx: RunContext, split: str = "test") -> dict[str, float]:
    """Distances of the last checkpoint's points to the GT (``split`` is ignored: there is one GT)."""
    pc = load_shape(cfg.data.shape, cfg.data.root or None)
    m = point_cloud_distances(restore(cfg, ctx).means.detach().cpu(), pc.points)
    results.info("%s", json.dumps(m, indent=2))
    return m


def render(cfg: Config, ctx: RunContext) -> list[Path]:
    """Write the held-out PNG renders of the last checkpoint."""
    pc = load_shape(cfg.data.shape, cfg.data.root or None)
    return write_renders(cfg, ctx, pc, restore(cfg, ctx))


def view(cfg: Config, ctx: RunContext) -> ViewModel:
    """The task contract's ``view``: the last checkpoint's surfels (shaded as trained) with the training
    cameras; their GT images only if already rendered (never re-rendered for viewing)."""
    pc = load_shape(cfg.data.shape, cfg.data.root or None)
    scene = restore(cfg, ctx)
    V, K = view_cameras(cfg.data.views, pc, cfg.data)
    images = cached_views(cfg.data, cfg.render, cfg.data.views)
    cams = TrainingCameras(V.to(ctx.device), K.to(ctx.device), cfg.data.width, cfg.data.height,
                           None if images is None else images.to(ctx.device))
    return surfel_view(scene, cams, shading=cfg.optim.shading, render_cfg=cfg.render, task="reconstruct",
                       seed=op_seed(ctx.seed, "eval"))
