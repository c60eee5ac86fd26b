"""Task ``reconstruct``: shape reconstruction from images (paper §4, Tables 1–3).

Data: ground-truth images of a DSS point cloud rendered with the exact dense renderer
(:func:`nsplat.ops.splat_dense`) under the paper's Lambert lights, black background, from random
views on a sphere around the object (cached under ``data_cache/``; views are nested: the first k of
a larger set are the k-view set). Init: a Fibonacci sphere enclosing the object. Optimisation:
:func:`nsplat.fitting.fit`. Outputs in the run folder: ``metrics.json`` (Hausdorff/Chamfer, both
definitions, see :mod:`nsplat.metrics`), ``reconstruction.ply``, ``renders/*.png`` (GT | result).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter

from nsplat.cameras import intrinsics_from_fov, look_at
from nsplat.checkpoint import load_checkpoint
from nsplat.config import ConfigError, require_fields
from nsplat.data.pointclouds import DSS_SHAPES, PointCloud, load_dss_shape
from nsplat.metrics import point_cloud_distances
from nsplat.fitting import FitConfig, fit
from nsplat import render as gateway
from nsplat.render import RenderConfig
from nsplat.runctx import RunContext
from nsplat.scene import SceneConfig, SurfelScene, knn_spacing
from nsplat.shading import lambert

log = logging.getLogger(__name__)
REPO_ROOT = Path(__file__).resolve().parents[2]
#: Bumped when ground-truth rendering changes, so stale caches are not reused.
GT_VERSION = 1


@dataclasses.dataclass
class DataConfig:
    """Ground-truth images.

    Attributes:
        shape: a DSS shape (bunny, teapot, yoga1, yoga6). root: data folder ("" = ``<repo>/../shared/data``).
        views: number of training views. width, height: image size in pixels.
        fov_deg: horizontal field of view. distance: camera distance from the object centre, in units of
            the enclosing-sphere radius. view_seed: seed of the view directions.
        gt_scale: GT splat std-dev in units of each point's mean 3-NN spacing. gt_albedo: GT albedo (grey).
        cache_dir: GT image cache ("" = ``<repo>/data_cache/reconstruct``).
    """

    shape: str = "bunny"
    root: str = ""
    views: int = 124
    width: int = 64
    height: int = 64
    fov_deg: float = 40.0
    distance: float = 3.0
    view_seed: int = 0
    gt_scale: float = 1.0
    gt_albedo: float = 1.0
    cache_dir: str = ""

    def __post_init__(self) -> None:
        if self.shape not in DSS_SHAPES:
            raise ConfigError(f"data.shape: expected one of {sorted(DSS_SHAPES)}, got {self.shape!r}")
        for key in ("views", "width", "height"):
            if getattr(self, key) < 1:
                raise ConfigError(f"data.{key}: expected >= 1, got {getattr(self, key)}")
        if not 0 < self.fov_deg < 180:
            raise ConfigError(f"data.fov_deg: expected in (0, 180), got {self.fov_deg}")
        if self.distance <= 1.0:
            raise ConfigError(f"data.distance: expected > 1 (cameras outside the object), got {self.distance}")


@dataclasses.dataclass
class InitConfig:
    """Initial surfels: a Fibonacci sphere about the object's centre.

    Attributes:
        count: number of points (null = the GT point count). radius: sphere radius in units of the
        enclosing-sphere radius. albedo: initial grey albedo. scale: initial std-dev in units of the
        sphere's mean 3-NN spacing.
    """

    count: int | None = None
    radius: float = 1.1
    albedo: float = 0.5
    scale: float = 1.0

    def __post_init__(self) -> None:
        require_fields(self, count=">=1", radius=">0", scale=">0")


@dataclasses.dataclass
class Config:
    """Task ``reconstruct``. ``eval_every``: epochs between metric evaluations (TensorBoard);
    ``renders``: number of held-out views rendered to PNG at the end."""

    task: str = "reconstruct"
    seed: int = 0
    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    init: InitConfig = dataclasses.field(default_factory=InitConfig)
    scene: SceneConfig = dataclasses.field(default_factory=SceneConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    optim: FitConfig = dataclasses.field(default_factory=FitConfig)
    eval_every: int = 10
    renders: int = 3

    def __post_init__(self) -> None:
        if self.scene.channels != 3:
            raise ConfigError(f"scene.channels: the reconstruct task shades RGB albedo, expected 3, "
                              f"got {self.scene.channels}")
        if self.optim.shading != "lambert":
            raise ConfigError("optim.shading: the reconstruct task's images are Lambert-shaded; expected 'lambert'")


# ---------------------------------------------------------------------------------------------- data
def view_cameras(count: int, pc: PointCloud, data: DataConfig, offset: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Cameras ``(viewmats [count,4,4], Ks [count,3,3])`` looking at the object's centre.

    View ``i`` has direction ``normalize(N(0, I))`` drawn from ``numpy.random.default_rng([view_seed, i])``,
    so view sets are nested; ``offset`` shifts the indices (held-out views use a large offset).
    """
    dirs = np.stack([np.random.default_rng([data.view_seed, offset + i]).normal(size=3) for i in range(count)])
    dirs = torch.as_tensor(dirs / np.linalg.norm(dirs, axis=1, keepdims=True), dtype=torch.float64)
    centre = pc.center.double()
    eye = centre + data.distance * pc.radius * dirs
    up = torch.where(dirs[:, 2:].abs() > 0.99, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                     torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    viewmats = look_at(eye, centre.expand_as(eye), up).float()
    Ks = intrinsics_from_fov(math.radians(data.fov_deg), data.width, data.height, count)
    return viewmats, Ks


def gt_scene(pc: PointCloud, data: DataConfig) -> dict[str, torch.Tensor]:
    """Op-ready GT surfels: isotropic std-dev ``gt_scale ×`` 3-NN spacing, opacity 1, grey albedo."""
    sp = torch.as_tensor(knn_spacing(pc.points), dtype=pc.points.dtype) * data.gt_scale
    n = pc.points.shape[0]
    return {"means": pc.points, "normals": pc.normals, "scales": sp[:, None].expand(n, 2).contiguous(),
            "opacities": torch.ones(n), "albedo": torch.full((n, 3), data.gt_albedo)}


def render_gt(pc: PointCloud, data: DataConfig, viewmats: torch.Tensor, Ks: torch.Tensor,
              render_cfg: RenderConfig) -> torch.Tensor:
    """GT images ``[B,H,W,3]`` with the exact dense renderer (Lambert, black background)."""
    gt = gt_scene(pc, data)
    out = []
    with torch.no_grad():
        shaded = lambert(gt["albedo"], gt["normals"], viewmats)
        for b in range(viewmats.shape[0]):
            out.append(gateway.render(gt["means"], gt["normals"], gt["scales"], gt["opacities"], shaded[b],
                              viewmats[b:b + 1], Ks[b:b + 1], data.width, data.height,
                              dataclasses.replace(render_cfg, renderer="dense")).image)
    return torch.cat(out, 0)


def _cache_file(data: DataConfig, render_cfg: RenderConfig, tag: str) -> Path:
    key = json.dumps({"v": GT_VERSION, "tag": tag, "shape": data.shape, "root": str(data.root),
                      "w": data.width, "h": data.height, "fov": data.fov_deg, "dist": data.distance,
                      "seed": data.view_seed, "gs": data.gt_scale, "ga": data.gt_albedo,
                      "lp": render_cfg.lowpass, "near": render_cfg.near, "far": render_cfg.far}, sort_keys=True)
    folder = Path(data.cache_dir) if data.cache_dir else REPO_ROOT / "data_cache" / "reconstruct"
    return folder / f"{data.shape}-{hashlib.sha1(key.encode()).hexdigest()[:12]}-{tag}.pt"


def cached_gt_images(pc: PointCloud, data: DataConfig, render_cfg: RenderConfig, count: int,
                     offset: int = 0, tag: str = "train") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(images [count,H,W,3], viewmats, Ks)`` of views ``offset … offset+count-1``, rendering only the
    views not yet in the cache (atomic write)."""
    viewmats, Ks = view_cameras(count, pc, data, offset)
    path = _cache_file(data, render_cfg, tag)
    have = torch.load(path, weights_only=True) if path.is_file() else torch.zeros(0, data.height, data.width, 3)
    if have.shape[0] < count:
        log.info("rendering %d GT views of %s at %dx%d (dense)", count - have.shape[0], data.shape,
                 data.width, data.height)
        extra = render_gt(pc, data, viewmats[have.shape[0]:], Ks[have.shape[0]:], render_cfg)
        have = torch.cat([have, extra], 0)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        torch.save(have, tmp)
        os.replace(tmp, path)
    return have[:count].clone(), viewmats, Ks


def fibonacci_sphere(count: int, centre: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(points [count,3], outward normals [count,3])`` evenly spread on a sphere."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    r = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    n = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)
    return (centre.double() + radius * n).float(), n.float()


def init_scene(pc: PointCloud, cfg: Config) -> SurfelScene:
    """The initial scene: ``init.count`` points on a sphere of radius ``init.radius ×`` the enclosing radius."""
    count = cfg.init.count if cfg.init.count is not None else pc.points.shape[0]
    if count < 4:
        raise ConfigError(f"init.count: expected >= 4, got {count}")
    means, normals = fibonacci_sphere(count, pc.center, cfg.init.radius * pc.radius)
    return SurfelScene.from_points(cfg.scene, means, normals, features=cfg.init.albedo, scale_factor=cfg.init.scale)


# ---------------------------------------------------------------------------------------------- run
def _load(cfg: Config, device: torch.device) -> tuple[PointCloud, torch.Tensor, torch.Tensor, torch.Tensor]:
    pc = load_dss_shape(cfg.data.shape, cfg.data.root or None)
    images, viewmats, Ks = cached_gt_images(pc, cfg.data, cfg.render, cfg.data.views)
    return pc, images.to(device), viewmats.to(device), Ks.to(device)


def run(cfg: Config, ctx: RunContext) -> dict[str, float]:
    """Reconstruct ``cfg.data.shape``; writes ``metrics.json``, ``reconstruction.ply`` and PNG renders."""
    torch.manual_seed(ctx.seed)
    t0 = time.time()
    pc, images, viewmats, Ks = _load(cfg, ctx.device)
    scene = init_scene(pc, cfg).to(ctx.device)
    init_metrics = point_cloud_distances(scene.means, pc.points)

    def on_epoch(epoch: int, sc: SurfelScene, writer: SummaryWriter) -> dict[str, float]:
        if (epoch + 1) % cfg.eval_every and epoch + 1 != cfg.optim.epochs:
            return {}
        m = point_cloud_distances(sc.means, pc.points)
        return {k: v for k, v in m.items() if k != "diagonal"}

    scalars = fit(scene, images, viewmats, Ks, cfg.optim, cfg.render, ctx.run_dir, seed=ctx.seed,
                  resume=ctx.resume, on_epoch=on_epoch)
    metrics = _finish(cfg, ctx, pc, scene)
    metrics.update(init={k: v for k, v in init_metrics.items()}, final_loss=scalars.get("loss"),
                   fit_seconds=time.time() - t0)
    _write_json(ctx.run_dir / "metrics.json", metrics)
    log.info("chamfer %.3e (sq %.3e)  hausdorff %.3e (sq %.3e)", metrics["chamfer"], metrics["chamfer_sq"],
             metrics["hausdorff"], metrics["hausdorff_sq"])
    return metrics


def _finish(cfg: Config, ctx: RunContext, pc: PointCloud, scene: SurfelScene) -> dict:
    scene.save_ply(ctx.run_dir / "reconstruction.ply")
    write_renders(cfg, ctx, pc, scene)
    m = point_cloud_distances(scene.means.detach().cpu(), pc.points)
    return {"shape": cfg.data.shape, "renderer": cfg.render.renderer, "estimator": cfg.render.estimator,
            "samples": cfg.render.samples, "views": cfg.data.views, "epochs": cfg.optim.epochs,
            "resolution": [cfg.data.width, cfg.data.height], "points": scene.num_points, "seed": ctx.seed, **m}


def _write_json(path: Path, obj: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=2))
    os.replace(tmp, path)


def _restore(cfg: Config, ctx: RunContext, pc: PointCloud) -> SurfelScene:
    scene = init_scene(pc, cfg)
    scene.load_state_dict(load_checkpoint(ctx.run_dir)["scene"])
    return scene.to(ctx.device)


def write_renders(cfg: Config, ctx: RunContext, pc: PointCloud, scene: SurfelScene) -> list[Path]:
    """PNGs ``renders/view_<i>.png`` of ``cfg.renders`` held-out views: GT | reconstruction, both
    rendered with the exact dense renderer; and ``renders/points.png``, a scatter plot of both clouds."""
    if cfg.renders < 1:
        return []
    images, viewmats, Ks = cached_gt_images(pc, cfg.data, cfg.render, cfg.renders, offset=1_000_000, tag="heldout")
    folder = ctx.run_dir / "renders"
    folder.mkdir(parents=True, exist_ok=True)
    dense = dataclasses.replace(cfg.render, renderer="dense")
    paths = []
    with torch.no_grad():
        sc = scene.cpu()
        shaded = lambert(sc.features, sc.normals, viewmats)
        for b in range(cfg.renders):
            rec = gateway.render(sc.means, sc.normals, sc.scales, sc.opacities, shaded[b], viewmats[b:b + 1], Ks[b:b + 1],
                         cfg.data.width, cfg.data.height, dense).image[0]
            pair = torch.cat([images[b], rec], 1).clamp(0, 1)
            p = folder / f"view_{b}.png"
            iio.imwrite(p, (pair.numpy() * 255).round().astype(np.uint8))
            paths.append(p)
    paths.append(write_point_plot(folder / "points.png", scene.means.detach().cpu(), pc))
    scene.to(ctx.device)
    return paths


def write_point_plot(path: Path, points: torch.Tensor, pc: PointCloud) -> Path:
    """Scatter plot ``path`` of the GT cloud and ``points [N,3]`` (coloured by distance to the GT, in units
    of the GT bounding-box diagonal, clipped at 0.1), from two directions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from nsplat.metrics import bbox_diagonal, nn_distances

    gt = pc.points.double().numpy()
    pred = points.double().numpy()
    dist = nn_distances(pred, gt) / bbox_diagonal(gt)
    fig = plt.figure(figsize=(7, 6))
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
    plt.close(fig)
    return path


def evaluate(cfg: Config, ctx: RunContext, split: str = "test") -> dict[str, float]:
    """Distances of the last checkpoint's points to the GT (``split`` is ignored: there is one GT)."""
    pc = load_dss_shape(cfg.data.shape, cfg.data.root or None)
    m = point_cloud_distances(_restore(cfg, ctx, pc).means.detach().cpu(), pc.points)
    log.info("%s", json.dumps(m, indent=2))
    return m


def render(cfg: Config, ctx: RunContext) -> list[Path]:
    """Write the held-out PNG renders of the last checkpoint."""
    pc = load_dss_shape(cfg.data.shape, cfg.data.root or None)
    return write_renders(cfg, ctx, pc, _restore(cfg, ctx, pc))
