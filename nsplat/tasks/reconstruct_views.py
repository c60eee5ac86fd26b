"""Ground-truth posed views of the shapes of Tables 1–3 (paper §4): the point clouds of
:mod:`nsplat.data.pointclouds` rendered under the paper's Lambert lights on a black background, from random
views on a sphere around the object, with :func:`nsplat.ops.splat_tiled`: the dense oracle's image to
``gt_tol`` (every kernel cut where it falls below ``gt_tol`` of its peak), at a cost of pixels × points in
reach (seconds for 124 views at 256², where the dense renderer takes about a minute a view).

Views are nested (the first k of a larger set are the k-view set) and cached one file a view under
``cache_dir`` (atomic writes) as soon as each is rendered: an interrupted run keeps its views, and only views
not yet cached are rendered, under a progress bar.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from nsplat.cameras import intrinsics_from_fov, look_at
from nsplat.config import require, require_fields
from nsplat.data.paths import resolve
from nsplat.data.pointclouds import PointCloud, check_shape
from nsplat.data.views import PosedViews
from nsplat.ops import splat_tiled
from nsplat.render.renderer import RenderConfig
from nsplat.render.shading import lambert
from nsplat.run.checkpoint import atomic_write
from nsplat.scene import knn_spacing

log = logging.getLogger(__name__)
#: Bumped when ground-truth rendering changes, so stale caches are not reused.
GT_VERSION = 3
#: Views rendered per call of the tiled renderer (then cached one file each).
GT_CHUNK = 4
#: Index offset of the held-out views (disjoint from any training set).
HELDOUT_OFFSET = 1_000_000


@dataclasses.dataclass
class DataConfig:
    """Ground-truth images.

    Attributes:
        shape: a DSS shape (bunny, teapot, yoga1, yoga6) or the path of a PLY point cloud (normals estimated when
            it has none; :func:`nsplat.data.pointclouds.load_shape`). root: data folder of the DSS shapes
            ("" = :func:`nsplat.data.paths.data_root`).
        views: number of training views. width, height: image size in pixels.
        fov_deg: horizontal field of view. distance: camera distance from the object centre, in units of
            the enclosing-sphere radius. view_seed: seed of the view directions.
        gt_scale: GT splat std-dev in units of each point's mean 3-NN spacing. gt_albedo: GT albedo (grey).
        gt_tol: the GT renderer's tolerance: kernels are cut where they fall below this fraction of their peak
            (:func:`nsplat.ops.splat_tiled`; 1e-7: the dense oracle's image to float precision).
        cache_dir: GT image cache ("" = ``<repo>/data_cache/reconstruct``; relative: to the repo root).
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
    gt_tol: float = 1e-7
    cache_dir: str = ""

    def __post_init__(self) -> None:
        check_shape(self.shape)
        require_fields(self, views=">=1", width=">=1", height=">=1", distance=">1", view_seed=">=0", gt_scale=">0",
                       gt_albedo="unit")
        require(0 < self.fov_deg < 180, "fov_deg", "a value in (0, 180)", self.fov_deg)
        require(0 < self.gt_tol < 1, "gt_tol", "a value in (0, 1)", self.gt_tol)



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
    """GT images with their coverage, ``[B,H,W,4]`` (RGB: Lambert on a black background; A: the accumulated
    opacity), rendered with :func:`nsplat.ops.splat_tiled` at ``data.gt_tol``."""
    gt = gt_scene(pc, data)
    shaded = lambert(gt["albedo"], gt["normals"], viewmats)
    out = splat_tiled(gt["means"], gt["normals"], gt["scales"], gt["opacities"], shaded, viewmats, Ks, data.width,
                      data.height, tol=data.gt_tol, near=render_cfg.near, far=render_cfg.far,
                      lowpass=render_cfg.lowpass)
    return torch.cat([out.image, out.alpha], -1)


def cache_folder(data: DataConfig, render_cfg: RenderConfig, tag: str) -> Path:
    """The folder caching one GT view a file (``<index>.pt``, RGBA ``[H,W,4]``) of this data, render and ``tag``."""
    key = json.dumps({"v": GT_VERSION, "tag": tag, "shape": str(data.shape), "root": str(data.root),
                      "w": data.width, "h": data.height, "fov": data.fov_deg, "dist": data.distance,
                      "seed": data.view_seed, "gs": data.gt_scale, "ga": data.gt_albedo, "tol": data.gt_tol,
                      "lp": render_cfg.lowpass, "near": render_cfg.near, "far": render_cfg.far}, sort_keys=True)
    folder = resolve(data.cache_dir or "data_cache/reconstruct")
    name = Path(data.shape).stem if data.shape.endswith(".ply") else data.shape
    return folder / f"{name}-{hashlib.sha1(key.encode()).hexdigest()[:12]}-{tag}"


def cached_views(data: DataConfig, render_cfg: RenderConfig, count: int, tag: str = "train") -> torch.Tensor | None:
    """The first ``count`` cached GT images ``[count,H,W,3]`` (RGB) of ``tag``, or ``None`` if any is missing."""
    folder = cache_folder(data, render_cfg, tag)
    paths = [folder / f"{i}.pt" for i in range(count)]
    if not all(p.is_file() for p in paths):
        return None
    return torch.stack([torch.load(p, weights_only=True)[..., :3] for p in paths])


def cached_gt_images(pc: PointCloud, data: DataConfig, render_cfg: RenderConfig, count: int,
                     offset: int = 0, tag: str = "train"
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(images [count,H,W,3], masks [count,H,W], viewmats, Ks)`` of views ``offset … offset+count-1``: the RGB
    images and their coverage (the GT's accumulated opacity). Views not yet cached are rendered ``GT_CHUNK`` at a
    time under a progress bar, each written to the cache (atomically) as it comes."""
    viewmats, Ks = view_cameras(count, pc, data, offset)
    folder = cache_folder(data, render_cfg, tag)
    paths = [folder / f"{i}.pt" for i in range(count)]
    missing = [i for i, p in enumerate(paths) if not p.is_file()]
    if missing:
        folder.mkdir(parents=True, exist_ok=True)
        log.info("rendering %d %s GT views of %s at %dx%d into %s", len(missing), tag, data.shape, data.width,
                 data.height, folder)
        with tqdm(total=len(missing), desc=f"GT views ({tag})", unit="view", dynamic_ncols=True) as bar:
            for j in range(0, len(missing), GT_CHUNK):
                chunk = missing[j:j + GT_CHUNK]
                images = render_gt(pc, data, viewmats[chunk], Ks[chunk], render_cfg)
                for i, image in zip(chunk, images):
                    atomic_write(paths[i], lambda fh, im=image: torch.save(im.clone(), fh))
                bar.update(len(chunk))
    rgba = torch.stack([torch.load(p, weights_only=True) for p in paths])
    return rgba[..., :3].contiguous(), rgba[..., 3].contiguous(), viewmats, Ks


def gt_views(pc: PointCloud, data: DataConfig, render_cfg: RenderConfig, count: int, *,
             heldout: bool = False) -> PosedViews:
    """The first ``count`` training views (or held-out views) of ``pc`` as :class:`PosedViews` (CPU), with the
    GT coverage as ``masks``."""
    tag, offset = ("heldout", HELDOUT_OFFSET) if heldout else ("train", 0)
    images, masks, viewmats, Ks = cached_gt_images(pc, data, render_cfg, count, offset=offset, tag=tag)
    return PosedViews(images, viewmats, Ks, [f"{tag}_{offset + i}" for i in range(count)], masks=masks)


