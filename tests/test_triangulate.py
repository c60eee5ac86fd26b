"""Points for a ``transforms.json`` folder that ships none (:mod:`nsplat.data.triangulate`): triangulated from the
photos with the file's poses held, or the SfM points of a COLMAP model beside the file, moved onto its cameras.

The fixture photographs the procedural scene in front of its textured environment (:mod:`nsplat.data.synthetic_capture`,
96 px, 12 views through a distorted ``OPENCV`` camera) and writes the true poses and intrinsics as an instant-ngp
``transforms.json`` without a point cloud, as ``colmap2nerf.py`` leaves one."""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from nsplat.cameras import camera_centres
from nsplat.config import load_config, read_yaml
from nsplat.data.capture import SfmPoints
from nsplat.data.procedural import make_scene, viewmat_to_opengl_c2w
from nsplat.data.raytrace import intersect
from nsplat.data.synthetic_capture import CaptureSpec, render_capture
from nsplat.data.transforms_json import load_transforms
from nsplat.data.triangulate import cached_triangulation, colmap_points_beside
from nsplat.tasks.neural.capture import prepare, start_kind
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.diagnosis import start_words
from nsplat.tasks.neural.starts import initial_geometry

REPO = Path(__file__).resolve().parents[1]
SPEC = CaptureSpec(seed=0, resolution=96, views=12, supersample=1)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """``scene/transforms.json`` (one OPENCV camera, the true poses, no ``ply_file_path``) + ``images/``."""
    root = tmp_path_factory.mktemp("tri") / "scene"
    rec = render_capture(SPEC, root)
    shutil.rmtree(root / "sparse_gt")
    shutil.rmtree(root / "masks")
    fx, fy, cx, cy, k1, k2, p1, p2 = SPEC.camera().params
    frames = []
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        V = np.eye(4)
        V[:3] = image.cam_from_world().matrix()
        frames.append({"file_path": f"images/{image.name}",
                       "transform_matrix": viewmat_to_opengl_c2w(torch.from_numpy(V)).tolist()})
    (root / "transforms.json").write_text(json.dumps(
        {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": SPEC.resolution,
         "h": SPEC.resolution, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "frames": frames}))
    return root


def _config(root: Path, downscale: int = 1) -> Config:
    raw = read_yaml(REPO / "configs" / "transforms.yaml")
    raw["data"] = {**raw["data"], "root": str(root), "capture": {**raw["data"]["capture"], "downscale": downscale}}
    raw["geometry"]["background"]["points"] = 1024
    return load_config(Config, raw)


def depth_error(xyz: torch.Tensor, viewmats: torch.Tensor) -> torch.Tensor:
    """``[P]`` float64: per world point of ``xyz [P,3]``, the smallest relative difference over the cameras
    ``viewmats [V,4,4]`` in front of which it lies between its distance and the true surface's along the same ray
    (the procedural objects or the environment sphere, ray-traced)."""
    prims, _ = make_scene(SPEC.seed, SPEC.objects)
    best = torch.full((len(xyz),), float("inf"), dtype=torch.float64)
    for V, o in zip(viewmats.double(), camera_centres(viewmats.double())):
        ray = xyz.double() - o
        dist = ray.norm(dim=1)
        d = ray / dist[:, None]
        origins = o.expand_as(d).contiguous()
        b = (origins * d).sum(-1)
        env = -b + torch.sqrt(b * b - (origins * origins).sum(-1) + SPEC.environment ** 2)
        truth = torch.minimum(intersect(origins, d, prims).t, env)
        front = (xyz.double() @ V[:3, :3].T + V[:3, 3])[:, 2] > 0
        err = torch.where(front, (truth - dist).abs() / dist, torch.inf)
        best = torch.minimum(best, err)
    return best


def test_auto_triangulates_points_on_the_true_surfaces_once(scene, tmp_path, caplog):
    cfg = _config(scene)
    with caplog.at_level(logging.INFO):
        prep = prepare(cfg)
        kind = start_kind(cfg)
        start = initial_geometry(cfg, prep.splits["train"], seed=0)
    lines = [r.getMessage() for r in caplog.records]
    assert kind == "triangulated" and prep.origin == "triangulated"
    assert any(line.startswith("triangulating points from the 9 training views") for line in lines)
    done = next(line for line in lines if line.startswith("triangulated ") and "posed views (96x96)" in line)
    assert len(prep.points) == int(done.split()[1]) >= 64
    # the points went through the capture's frame, as a COLMAP capture's SfM points do: back to the world
    f = prep.frame
    world = f.centre + (prep.points.xyz.double() / f.scale) @ f.rotation
    assert np.allclose(prep.to_training(world).numpy(), prep.points.xyz.numpy(), atol=1e-4)
    truth = load_transforms(scene, holdout_every=cfg.data.capture.holdout_every)
    err = depth_error(world, torch.cat([truth.train.viewmats, truth.test.viewmats]))
    # on the objects or the environment: 99 % within 3 % of the true depth (random points in the scene: 11 %)
    assert float((err < 0.03).double().mean()) > 0.9
    # the start: the filtered points (sfm_surfels), then the fill and the background sphere
    kept = next(line for line in lines if line.startswith("SfM init:") and "triangulated points kept" in line)
    n = int(kept.split()[2])
    assert 0.8 * len(prep.points) <= n <= len(prep.points)
    sfm_part = f.centre + (start.means.detach()[:n].double() / f.scale) @ f.rotation
    assert float((depth_error(sfm_part, truth.train.viewmats) < 0.03).double().mean()) > 0.9
    assert "the start was the" in start_words(cfg, kind) and "\n" not in start_words(cfg, kind)
    # training at 48 px triangulates the same photos at 96 px (finer than they train at): read from the cache
    caplog.clear()
    with caplog.at_level(logging.INFO):
        half = prepare(_config(scene, downscale=2))
    assert half.splits["train"].width == 48 and half.origin == "triangulated"
    assert torch.equal(half.points.xyz, prep.points.xyz)  # the same frame: the cameras' and points' similarity
    assert any(r.getMessage().startswith("triangulated points: ") and "from the cache" in r.getMessage()
               for r in caplog.records)
    # cached: the second triangulation of the same views is read back
    caplog.clear()
    views = load_transforms(scene, holdout_every=0).train
    with caplog.at_level(logging.INFO):
        first = cached_triangulation(views, tmp_path / "cache")
        again = cached_triangulation(views, tmp_path / "cache")
    assert any("from the cache" in r.getMessage() for r in caplog.records)
    assert torch.equal(first.xyz, again.xyz) and torch.equal(first.track_length, again.track_length)


def _model(points: SfmPoints, viewmats: torch.Tensor, names: list[str], sim: pycolmap.Sim3d) -> pycolmap.Reconstruction:
    """A COLMAP model of the cameras ``viewmats [V,4,4]`` (named ``names``) and ``points``, moved by ``sim``."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(SPEC.camera())
    for i, (V, name) in enumerate(zip(viewmats.double().numpy(), names)):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(V[:3, :3]), V[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(image_id=i + 1, name=name, camera_id=1), pose)
    for xyz, rgb in zip(points.xyz.double().numpy(), points.rgb.numpy()):
        rec.add_point3D(xyz, pycolmap.Track(), (rgb * 255).astype(np.uint8))
    rec.transform(sim)
    return rec


def test_a_colmap_model_beside_the_file_gives_its_points_on_the_file_cameras(scene, tmp_path, caplog):
    views = load_transforms(scene, holdout_every=0).train
    rng = np.random.default_rng(0)
    points = SfmPoints(xyz=torch.from_numpy(rng.uniform(-1, 1, (200, 3))).float(), rgb=torch.rand(200, 3),
                       track_length=torch.full((200,), 3), error=torch.zeros(200))
    names = [Path(n).name for n in views.names]  # COLMAP names images relative to images/
    sim = pycolmap.Sim3d(2.5, pycolmap.Rotation3d(np.array([0.2, -0.4, 0.9])), np.array([1.0, -3.0, 0.5]))
    beside = tmp_path / "scene"
    beside.mkdir()
    for entry in scene.iterdir():
        (beside / entry.name).symlink_to(entry)
    (beside / "colmap" / "sparse" / "0").mkdir(parents=True)
    _model(points, views.viewmats, names, sim).write_binary(str(beside / "colmap" / "sparse" / "0"))
    found = colmap_points_beside(beside, views)
    assert found is not None and found[1] == beside / "colmap" / "sparse" / "0"
    assert torch.allclose(found[0].xyz, points.xyz, atol=1e-4)  # back in the file's world
    cfg = _config(beside)
    assert start_kind(cfg) == "sfm" and prepare(cfg).origin == str(found[1])
    # a model of other cameras (every camera moved a random amount) is passed over with a warning
    moved = views.viewmats.clone()
    moved[:, :3, 3] += torch.from_numpy(rng.normal(0, 0.5, (len(views), 3))).float()
    (beside / "sparse" / "0").mkdir(parents=True)
    _model(points, moved, names, sim).write_binary(str(beside / "sparse" / "0"))
    with caplog.at_level(logging.WARNING):
        found = colmap_points_beside(beside, views)
    assert found is not None and found[1] == beside / "colmap" / "sparse" / "0"  # the next folder
    warning = next(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert "sparse/0" in warning and "do not fit" in warning and "\n" not in warning
