"""Ground truth of the reconstruction task: any PLY as the shape (normals estimated when missing), GT views
rendered with the tiled renderer (exact against the dense oracle), cached a view at a time, and the task's
outputs (progress bar with the Chamfer distance, renders, metrics on stdout)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from plyfile import PlyData, PlyElement

import nsplat.tasks.reconstruct_views as dss
from nsplat.cli import main as cli_main
from nsplat.config import ConfigError
from nsplat.data.pointclouds import estimate_normals, load_shape
from nsplat.errors import DataError
from nsplat.evaluation.shape_metrics import point_cloud_distances
from nsplat.ops import splat_dense
from nsplat.render.renderer import RenderConfig
from nsplat.render.shading import lambert
from nsplat.tasks.reconstruct import Config, InitConfig, fibonacci_sphere, hull_init
from nsplat.tasks.reconstruct_views import DataConfig, cached_gt_images, gt_scene, view_cameras
from tests.conftest import write_dss_ply


def _plain_ply(path: Path, points: int = 500, normals: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """An ellipsoid's points (and outward normals) as a PLY with ``x y z`` and, optionally, ``nx ny nz``."""
    g = np.random.default_rng(1)
    d = g.normal(size=(points, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    axes = np.array([1.0, 0.6, 0.4])
    xyz, nrm = d * axes, d / axes
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    names = ("x", "y", "z", "nx", "ny", "nz") if normals else ("x", "y", "z")
    vertex = np.empty(points, dtype=[(k, "<f4") for k in names])
    for i, k in enumerate("xyz"):
        vertex[k] = xyz[:, i]
        if normals:
            vertex[f"n{k}"] = nrm[:, i]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    return xyz, nrm


def test_a_ply_path_is_a_shape_and_missing_normals_are_estimated(tmp_path):
    xyz, nrm = _plain_ply(tmp_path / "egg.ply")
    pc = load_shape(str(tmp_path / "egg.ply"))
    assert pc.name == "egg" and torch.allclose(pc.points, torch.as_tensor(xyz, dtype=torch.float32))
    agree = (pc.normals.double() * torch.as_tensor(nrm)).sum(1)
    assert float((agree > 0).double().mean()) > 0.99          # oriented outwards
    assert float(agree.abs().median()) > 0.98                # and along the true normal
    _plain_ply(tmp_path / "oriented.ply", normals=True)
    given = load_shape(str(tmp_path / "oriented.ply"))
    assert torch.allclose(given.normals.double(), torch.as_tensor(nrm), atol=1e-6)


def test_normals_are_oriented_per_component(tmp_path):
    """Two separate ellipsoids: each connected part of the neighbour graph gets its own outward seed."""
    xyz, nrm = _plain_ply(tmp_path / "a.ply", points=400)
    both = torch.as_tensor(np.concatenate([xyz, xyz + [5.0, 0.0, 0.0]]))
    est = estimate_normals(both)
    true = torch.as_tensor(np.concatenate([nrm, nrm]))
    assert float(((est * true).sum(1) > 0).double().mean()) > 0.99


@pytest.mark.parametrize("content, match", [(b"not a ply", "not a PLY"), (None, "no PLY file")])
def test_bad_shape_files_are_named(tmp_path, content, match):
    path = tmp_path / "bad.ply"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises((DataError, FileNotFoundError), match=match):
        load_shape(str(path))
    with pytest.raises(ConfigError, match="data.shape"):
        DataConfig(shape="dragon")


def test_gt_views_match_the_dense_oracle(tmp_path):
    """The GT renderer (tiled, gt_tol 1e-7) gives the dense oracle's images to float rounding."""
    write_dss_ply(tmp_path / "dss_pointclouds" / "bunny-8000.ply", points=300)
    pc = load_shape("bunny", tmp_path)
    data = DataConfig(shape="bunny", root=str(tmp_path), views=3, width=20, height=18, cache_dir=str(tmp_path / "c"))
    rc = RenderConfig()
    images, masks, V, K = cached_gt_images(pc, data, rc, 3)
    gt = gt_scene(pc, data)
    ref = splat_dense(gt["means"], gt["normals"], gt["scales"], gt["opacities"],
                      lambert(gt["albedo"], gt["normals"], V), V, K, 20, 18, lowpass=rc.lowpass)
    assert images.shape == (3, 18, 20, 3) and float(images.max()) > 0.3
    assert float((images - ref.image).abs().max()) < 2e-6
    assert masks.shape == (3, 18, 20) and float(masks.max()) > 0.9 and float(masks.min()) < 0.1
    assert float((masks - ref.alpha[..., 0]).abs().max()) < 2e-6


def test_gt_views_are_cached_as_rendered_and_an_interrupted_run_keeps_them(tmp_path, monkeypatch):
    write_dss_ply(tmp_path / "dss_pointclouds" / "bunny-8000.ply", points=200)
    pc = load_shape("bunny", tmp_path)
    data = DataConfig(shape="bunny", root=str(tmp_path), views=10, width=12, height=12, cache_dir=str(tmp_path / "c"))
    rc = RenderConfig()
    rendered: list[int] = []
    real = dss.render_gt

    def counting(pc, data, viewmats, Ks, render_cfg):
        if rendered and len(rendered) >= 2 * dss.GT_CHUNK and not counting.resumed:
            raise KeyboardInterrupt
        rendered.extend(range(viewmats.shape[0]))
        return real(pc, data, viewmats, Ks, render_cfg)

    counting.resumed = False
    monkeypatch.setattr(dss, "render_gt", counting)
    with pytest.raises(KeyboardInterrupt):
        cached_gt_images(pc, data, rc, 10)
    assert len(list(dss.cache_folder(data, rc, "train").glob("*.pt"))) == 2 * dss.GT_CHUNK
    counting.resumed = True
    images, masks, V, K = cached_gt_images(pc, data, rc, 10)
    assert len(rendered) == 10                                  # the cached views were not rendered again
    vm, K = view_cameras(10, pc, data)
    fresh = torch.cat([real(pc, data, vm[s:s + dss.GT_CHUNK], K[s:s + dss.GT_CHUNK], rc)   # as cached: by chunk
                       for s in range(0, 10, dss.GT_CHUNK)])
    assert torch.equal(images, fresh[..., :3]) and torch.equal(masks, fresh[..., 3])
    assert torch.equal(cached_gt_images(pc, data, rc, 4)[0], images[:4])   # nested: the first k views


def test_task_on_a_ply_path_shows_chamfer_and_prints_metrics(tmp_path, capsys):
    _plain_ply(tmp_path / "egg.ply", points=300)
    cfg = {"task": "reconstruct", "seed": 0,
           "data": {"shape": str(tmp_path / "egg.ply"), "views": 4, "width": 16, "height": 16,
                    "cache_dir": str(tmp_path / "cache")},
           "init": {"count": 60}, "render": {"samples": 4}, "optim": {"epochs": 2, "batch": 2},
           "log": {"validate": 2, "checkpoint": 4}, "heldout": 3, "renders": 2}
    (tmp_path / "egg.yaml").write_text(yaml.safe_dump(cfg))
    run = tmp_path / "run"
    assert cli_main(["--config", str(tmp_path / "egg.yaml"), "--run", str(run)]) == 0
    out, err = capsys.readouterr()
    assert "chamfer" in out and "held-out PSNR" in out and "shape/chamfer=" in err  # stdout; Chamfer on the bar
    assert (run / "renders" / "view_1.png").is_file() and (run / "renders" / "points.png").is_file()
    assert not (run / "renders" / "view_2.png").exists()             # 3 views scored, 2 written
    assert (run / "reconstruction.ply").is_file()
    metrics = json.loads((run / "metrics.json").read_text())
    assert 5.0 < metrics["heldout_psnr"] < 60.0


def test_hull_init_lies_on_the_shape_with_the_asked_count(tmp_path):
    """``init.kind: hull``: points on the visual hull of the training coverage; far closer to the shape than the
    paper's enclosing sphere, with outward normals, exactly ``count`` of them whether the hull's surface has more
    voxels or fewer (then the repeats are moved within their voxel's tangent plane)."""
    _plain_ply(tmp_path / "egg.ply", points=1500, normals=True)        # an ellipsoid with axes 1, 0.6, 0.4
    pc = load_shape(str(tmp_path / "egg.ply"))
    data = DataConfig(shape=str(tmp_path / "egg.ply"), views=24, width=32, height=32, cache_dir=str(tmp_path / "c"))
    views = dss.gt_views(pc, data, RenderConfig(), 24)
    assert views.masks is not None and views.masks.shape == (24, 32, 32)
    sphere, _ = fibonacci_sphere(500, pc.center, 1.1 * pc.radius)
    far = point_cloud_distances(sphere, pc.points)["chamfer"]
    for count in (150, 3000):
        means, normals = hull_init(views, count, pc.center, 1.1 * float(pc.radius), 32, 0.5, seed=0)
        assert means.shape == normals.shape == (count, 3)
        near = point_cloud_distances(means, pc.points)["chamfer"]
        assert near < far / 4, (near, far)                        # measured 0.034 (150), 0.021 (3000) vs 0.18
        outward = ((means - pc.center) * normals).sum(-1) > 0
        assert float(outward.float().mean()) > 0.95
        assert torch.unique(means, dim=0).shape[0] == count        # repeats are moved, not stacked
    with pytest.raises(ConfigError, match="kind"):
        InitConfig(kind="cube")
    with pytest.raises(ConfigError, match="renders"):
        Config(heldout=2, renders=3)
