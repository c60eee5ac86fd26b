"""The scene's box from its cameras and silhouettes (:func:`nsplat.data.visual_hull.silhouette_box`, issue 70).

An analytic oracle: the silhouettes of a box-shaped object (ray–box intersection per pixel) seen from cameras
around it. The box found must contain the object and exceed it by no more than a voxel of the last carving grid
plus the margin; moving and scaling the scene with a similarity transform of its cameras moves and scales the box
with it, including far outside lego's hand-written box (the trap of issue 70: a chair whose legs leave it).
The neural task takes the box from the data unless ``geometry.bbox`` overrides it.
"""
from __future__ import annotations

import logging
import math

import pytest
import torch

from nsplat.cameras import intrinsics_from_fov, sphere_views
from nsplat.config import ConfigError, load_config
from nsplat.data.views import PosedViews
from nsplat.data.visual_hull import silhouette_box
from nsplat.tasks.neural.config import FRAME_BOX, Config, GeometryConfig
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.starts import initial_geometry

LEGO_BOX = (-0.8, -1.3, -0.75, 0.8, 1.3, 1.15)
SIZE = 48
FOV = 0.9


def box_silhouettes(lo: torch.Tensor, hi: torch.Tensor, viewmats: torch.Tensor, size: int = SIZE) -> PosedViews:
    """Views ``size²`` of the axis-aligned box ``[lo, hi]`` whose masks are 1 where the pixel's ray hits it."""
    K = intrinsics_from_fov(FOV, size, size, batch=len(viewmats)).double()
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64) + 0.5,
                          torch.arange(size, dtype=torch.float64) + 0.5, indexing="ij")
    masks = []
    for vm, k in zip(viewmats.double(), K):
        d_cam = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], -1)
        R, t = vm[:3, :3], vm[:3, 3]
        origin = -R.T @ t
        d = d_cam @ R                                  # world directions (rows: R^T d_cam)
        inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t0, t1 = (lo - origin) * inv, (hi - origin) * inv
        near = torch.minimum(t0, t1).amax(-1)
        far = torch.maximum(t0, t1).amin(-1)
        masks.append((far >= near.clamp_min(0.0)).float())
    n = len(viewmats)
    return PosedViews(images=torch.zeros(n, size, size, 3), viewmats=viewmats.float(), Ks=K.float(),
                      names=[str(i) for i in range(n)], masks=torch.stack(masks).float())


def _check_encloses(box: tuple[float, ...], lo: torch.Tensor, hi: torch.Tensor, distance: float,
                    margin: float = 0.05, grid: int = 48, dilate: int = 1) -> None:
    """``box`` holds ``[lo, hi]`` and exceeds it per side by at most what the search allows: the silhouettes'
    dilation plus the nearest-pixel lookup (``dilate + 1`` pixels at the farthest depth, ``distance``), two voxels
    of the last grid and the margin."""
    found_lo, found_hi = torch.tensor(box[:3], dtype=torch.float64), torch.tensor(box[3:], dtype=torch.float64)
    assert (found_lo <= lo).all() and (found_hi >= hi).all(), (box, lo, hi)
    pixel = 2.0 * math.tan(FOV / 2) * distance / SIZE
    found = (found_hi - found_lo) / (1 + 2 * margin)
    allowed = (dilate + 1) * pixel + 2 * found / grid + margin * found
    assert ((lo - found_lo) <= allowed).all() and ((found_hi - hi) <= allowed).all(), (box, lo, hi, allowed)


def test_the_box_encloses_the_object_tightly():
    lo, hi = torch.tensor([-0.3, -0.5, -0.2], dtype=torch.float64), torch.tensor([0.4, 0.5, 0.6], dtype=torch.float64)
    views = box_silhouettes(lo, hi, sphere_views(40, 4.0, seed=1, target=(0.05, 0.0, 0.2)))
    _check_encloses(silhouette_box(views), lo, hi, distance=4.0 + float((hi - lo).norm()))


@pytest.mark.parametrize("scale,shift", [(3.0, (5.0, -4.0, 2.0)), (0.25, (-0.5, 2.5, -3.0))])
def test_a_similarity_of_the_scene_moves_the_box_with_it(scale, shift):
    """The same object and cameras moved by ``x -> scale·x + shift``: the box follows, well outside lego's box."""
    lo0, hi0 = torch.tensor([-0.3, -0.5, -0.2], dtype=torch.float64), torch.tensor([0.4, 0.5, 0.6],
                                                                                   dtype=torch.float64)
    shift_t = torch.tensor(shift, dtype=torch.float64)
    lo, hi = scale * lo0 + shift_t, scale * hi0 + shift_t
    target = tuple((scale * torch.tensor([0.05, 0.0, 0.2], dtype=torch.float64) + shift_t).tolist())
    views = box_silhouettes(lo, hi, sphere_views(40, 4.0 * scale, seed=1, target=target))
    box = silhouette_box(views)
    _check_encloses(box, lo, hi, distance=scale * (4.0 + float((hi0 - lo0).norm())))
    outside = [box[i] < LEGO_BOX[i] for i in range(3)] + [box[i + 3] > LEGO_BOX[i + 3] for i in range(3)]
    assert any(outside)  # the hand-written box would have cut this scene


def test_an_empty_hull_is_a_clear_error():
    views = box_silhouettes(torch.zeros(3, dtype=torch.float64), torch.full((3,), 0.5, dtype=torch.float64),
                            sphere_views(12, 4.0, seed=2))
    views.masks[0] = 0.0  # one view sees nothing: no voxel lies inside every silhouette
    with pytest.raises(ValueError, match="inside every silhouette"):
        silhouette_box(views)


def test_geometry_bbox_is_from_the_data_unless_set():
    assert GeometryConfig().bbox is None
    assert GeometryConfig(bbox=LEGO_BOX).bbox == LEGO_BOX
    assert FRAME_BOX == (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
    with pytest.raises(ConfigError, match="bbox"):
        GeometryConfig(bbox=(0.0, 0.0, 0.0, -1.0, 1.0, 1.0))


def _procedural(tmp_path, **geometry) -> Config:
    return load_config(Config, {"task": "neural", "data": {"procedural": {
        "seed": 1, "resolution": 24, "views": [6, 2, 2], "objects": 2, "cache_dir": str(tmp_path)}},
        "geometry": {"grid": 24, **geometry}})


def test_the_hull_start_is_carved_in_the_box_from_the_data(tmp_path, caplog):
    cfg = _procedural(tmp_path)
    train = load_views(cfg, "train", torch.device("cpu"))
    with caplog.at_level(logging.INFO, logger="nsplat"):
        scene = initial_geometry(cfg, train, seed=0)
    assert "the scene's box from the training silhouettes" in caplog.text
    box = torch.tensor(silhouette_box(train), dtype=torch.float32)
    means = scene.means.detach()
    assert ((means >= box[:3]) & (means <= box[3:])).all()


def test_a_box_that_misses_the_scene_is_a_one_line_config_error(tmp_path):
    cfg = _procedural(tmp_path, bbox=[5.0, 5.0, 5.0, 6.0, 6.0, 6.0])
    train = load_views(cfg, "train", torch.device("cpu"))
    with pytest.raises(ConfigError, match=r"geometry\.bbox: .*visual hull is empty.*null takes the scene's box"):
        initial_geometry(cfg, train, seed=0)
