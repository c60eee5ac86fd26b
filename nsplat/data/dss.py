"""Ground-truth posed views of the DSS shapes (paper §4, Tables 1–3): the point clouds of
:mod:`nsplat.data.pointclouds` rendered with the exact dense renderer under the paper's Lambert lights on
a black background, from random views on a sphere around the object.

Views are nested (the first k of a larger set are the k-view set) and cached under ``cache_dir``
(atomic writes; only views not yet cached are rendered).
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

from nsplat import render as gateway
from nsplat.cameras import intrinsics_from_fov, look_at
from nsplat.checkpoint import atomic_write
from nsplat.config import require, require_fields
from nsplat.data.paths import resolve
from nsplat.data.pointclouds import DSS_SHAPES, PointCloud
from nsplat.data.views import PosedViews
from nsplat.render import RenderConfig
from nsplat.scene import knn_spacing
from nsplat.shading import lambert

log = logging.getLogger(__name__)
#: Bumped when ground-truth rendering changes, so stale caches are not reused.
GT_VERSION = 1
#: Index offset of the held-out views (disjoint from any training set).
HELDOUT_OFFSET = 1_000_000


@dataclasses.dataclass
class DataConfig:
    """Ground-truth images.

    Attributes:
        shape: a DSS shape (bunny, teapot, yoga1, yoga6). root: data folder ("" = :func:`nsplat.data.paths.data_root`).
        views: number of training views. width, height: image size in pixels.
        fov_deg: horizontal field of view. distance: camera distance from the object centre, in units of
            the enclosing-sphere radius. view_seed: seed of the view directions.
        gt_scale: GT splat std-dev in units of each point's mean 3-NN spacing. gt_albedo: GT albedo (grey).
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
    cache_dir: str = ""

    def __post_init__(self) -> None:
        require(self.shape in DSS_SHAPES, "shape", f"one of {sorted(DSS_SHAPES)}", self.shape)
        require_fields(self, views=">=1", width=">=1", height=">=1", distance=">1", view_seed=">=0", gt_scale=">0",
                       gt_albedo="unit")
        require(0 < self.fov_deg < 180, "fov_deg", "a value in (0, 180)", self.fov_deg)



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


def cache_file(data: DataConfig, render_cfg: RenderConfig, tag: str) -> Path:
    key = json.dumps({"v": GT_VERSION, "tag": tag, "shape": data.shape, "root": str(data.root),
                      "w": data.width, "h": data.height, "fov": data.fov_deg, "dist": data.distance,
                      "seed": data.view_seed, "gs": data.gt_scale, "ga": data.gt_albedo,
                      "lp": render_cfg.lowpass, "near": render_cfg.near, "far": render_cfg.far}, sort_keys=True)
    folder = resolve(data.cache_dir or "data_cache/reconstruct")
    return folder / f"{data.shape}-{hashlib.sha1(key.encode()).hexdigest()[:12]}-{tag}.pt"


def cached_gt_images(pc: PointCloud, data: DataConfig, render_cfg: RenderConfig, count: int,
                     offset: int = 0, tag: str = "train") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(images [count,H,W,3], viewmats, Ks)`` of views ``offset … offset+count-1``, rendering only the
    views not yet in the cache (atomic write)."""
    viewmats, Ks = view_cameras(count, pc, data, offset)
    path = cache_file(data, render_cfg, tag)
    have = torch.load(path, weights_only=True) if path.is_file() else torch.zeros(0, data.height, data.width, 3)
    if have.shape[0] < count:
        log.info("rendering %d GT views of %s at %dx%d (dense)", count - have.shape[0], data.shape,
                 data.width, data.height)
        extra = render_gt(pc, data, viewmats[have.shape[0]:], Ks[have.shape[0]:], render_cfg)
        have = torch.cat([have, extra], 0)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, lambda fh: torch.save(have, fh))
    return have[:count].clone(), viewmats, Ks


def gt_views(pc: PointCloud, data: DataConfig, render_cfg: RenderConfig, count: int, *,
             heldout: bool = False) -> PosedViews:
    """The first ``count`` training views (or held-out views) of ``pc`` as :class:`PosedViews` (CPU)."""
    tag, offset = ("heldout", HELDOUT_OFFSET) if heldout else ("train", 0)
    images, viewmats, Ks = cached_gt_images(pc, data, render_cfg, count, offset=offset, tag=tag)
    return PosedViews(images, viewmats, Ks, [f"{tag}_{offset + i}" for i in range(count)])


