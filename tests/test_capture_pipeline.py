"""The COLMAP path end to end on a capture made here (:mod:`nsplat.data.synthetic_capture`): the procedural
scene photographed in front of a textured environment through a distorted ``OPENCV`` camera, no masks used,
reconstructed by pycolmap's SfM on the CPU (regenerated once per test session, about 15 s). pycolmap's
model is checked against the ground truth that rendered the photos, the training frame against the loaded
cameras, and ``configs/colmap.yaml`` trains a few steps on it and evaluates the every-8th held-out views. The
same capture, and one on a full orbit, train to the same PSNR after a random similarity of the SfM world; a run
that cannot learn stops with a message."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import pytest
import torch
import yaml
from scipy.spatial.transform import Rotation

from nsplat.cameras import camera_centres
from nsplat.cli import main
from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.data.colmap import load_colmap
from nsplat.data.procedural import camera_poses, make_scene
from nsplat.data.raytrace import camera_rays, render, shade
from nsplat.data.synthetic_capture import CaptureSpec, ensure_capture
from nsplat.errors import DataError
from nsplat.tasks.neural.background import project
from nsplat.tasks.neural.capture import prepare, with_capture_render
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.sfm_init import fill_box
from nsplat.tasks.neural.starts import _sfm_points, initial_geometry

REPO = Path(__file__).resolve().parents[1]
SPEC = CaptureSpec(resolution=128, views=24)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return ensure_capture(SPEC, tmp_path_factory.mktemp("captures"))


def _centres(views) -> np.ndarray:
    return camera_centres(views.viewmats.double()).numpy()


def test_sfm_registers_every_photo_and_recovers_the_true_cameras(capture):
    sfm = json.loads((capture / "sfm.json").read_text())
    assert sfm["registered"] == sfm["images"] == SPEC.views and sfm["points"] > 300
    est = load_colmap(capture, holdout_every=0)
    gt = load_colmap(capture, holdout_every=0, sparse="sparse_gt/0", masks="masks")
    assert est.train.names == gt.train.names == sorted(f"im_{i:03d}.png" for i in range(SPEC.views))
    sim = pycolmap.estimate_sim3d(_centres(est.train).astype(np.float64), _centres(gt.train).astype(np.float64))
    aligned = np.array([sim.matrix() @ np.append(c, 1.0) for c in _centres(est.train)])
    err = np.linalg.norm(aligned - _centres(gt.train), axis=1)
    assert err.max() < 0.01 * SPEC.radius                  # camera centres within 1 % of their distance
    R_sim = sim.rotation.matrix()
    for Ve, Vg in zip(est.train.viewmats.double().numpy(), gt.train.viewmats.double().numpy()):
        dR = Ve[:3, :3] @ R_sim.T @ Vg[:3, :3].T
        assert math.degrees(math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.3
    cam = next(iter(est.cameras.values()))
    assert cam.model_name == "OPENCV"
    assert cam.focal_length_x == pytest.approx(SPEC.camera().focal_length_x, rel=0.06)
    # the ground-truth model loads to exactly the camera and poses that rendered the photos
    assert next(iter(gt.cameras.values())).params.tolist() == SPEC.camera().params.tolist()
    truth = camera_poses(SPEC.views, SPEC.radius, SPEC.elevation, np.random.default_rng([SPEC.seed, 2]))
    assert (gt.train.viewmats - truth.float()).abs().max().item() < 1e-6  # the rotation is stored as a quaternion
    # masks: undistorted like the photos; objects cover part of each view, the environment the rest
    assert gt.train.masks is not None and gt.train.masks.shape == gt.train.images.shape[:3]
    cover = (gt.train.masks > 0.5).float().mean((1, 2))
    assert bool((cover > 0.02).all()) and bool((cover < 0.6).all())


def test_photos_have_no_blank_pixels_and_the_ray_tracer_refactor_is_exact(capture):
    img = iio.imread(capture / "images" / "im_000.png")
    assert img.shape == (SPEC.resolution, SPEC.resolution, 3) and img.reshape(-1, 3).max(1).min() > 0
    # render() is shade() averaged per pixel: the procedural scenes are unchanged by the split
    prims, light = make_scene(0, 3)
    V = torch.eye(4, dtype=torch.float64)
    V[2, 3] = 3.0
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]], dtype=torch.float64)
    rgba = render(prims, light, V, K, 16, 16, supersample=2)
    rgb, found = shade(prims, light, *camera_rays(V, K, 16, 16, 2))
    cover = found.double().reshape(16, 16, 4)
    assert torch.equal(rgba[..., 3], cover.mean(-1))
    assert torch.equal(rgba[..., :3], rgb.reshape(16, 16, 4, 3).sum(2) / cover.sum(-1, keepdim=True).clamp_min(1.0))


def _config(capture: Path, **geometry) -> dict:
    raw = read_yaml(REPO / "configs" / "colmap.yaml")
    raw["data"]["root"] = str(capture)
    raw["data"]["capture"]["downscale"] = 4
    raw["geometry"].update({"optim": {"epochs": 1, "batch": 2}, **geometry})
    raw["geometry"]["background"]["points"] = 2048
    raw["neural"].update({"steps": 4, "batch": 2, "features": 4, "unet": {"depth": 2, "width": 8},
                          "gan": {"enabled": True, "width": 8, "layers": 2, "start": 0.5}})
    raw["log"] = {"every": 1, "images": 0, "checkpoint": 2, "validate": 2, "progress": False}
    raw["eval"].update({"draws": 1, "val_views": 2})
    return raw


def test_training_frame_is_a_similarity_of_the_capture(capture):
    cfg = load_config(Config, _config(capture))
    prep = prepare(cfg)
    assert [len(prep.splits[k]) for k in ("train", "val", "test")] == [18, 3, 3]
    assert prep.splits["test"].names == ["im_000.png", "im_008.png", "im_016.png"]
    assert prep.splits["val"].names == ["im_005.png", "im_014.png", "im_023.png"]  # every 8th of the rest, from the 4th
    raw = load_colmap(capture, downscale=4)
    allv = torch.cat([prep.splits[k].viewmats for k in ("train", "val", "test")])
    centre, radius = prep.centre()
    assert centre.norm().item() == 0.0 and radius == pytest.approx(cfg.data.capture.radius, rel=1e-9)
    assert camera_centres(allv.double()).norm(dim=1).median().item() == pytest.approx(radius, rel=1e-5)
    # every SfM point in view lands on the same pixel through the moved camera as through the loaded one
    train_raw = raw.train.subset([raw.train.names.index(n) for n in prep.splits["train"].names])
    size = torch.tensor([train_raw.width, train_raw.height], dtype=torch.float64)
    for Vn, Vr, K in zip(prep.splits["train"].viewmats[:4], train_raw.viewmats[:4], train_raw.Ks[:4]):
        def pix(V: torch.Tensor, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            c = X.double() @ V[:3, :3].double().T + V[:3, 3].double()
            p = c @ K.double().T
            return p[:, :2] / p[:, 2:], c[:, 2]
        (a, depth), (b, _) = pix(Vn, prep.points.xyz), pix(Vr, raw.points.xyz)
        seen = (depth > 0.1) & ((b >= 0) & (b <= size)).all(1)
        assert int(seen.sum()) > 100
        assert (a[seen] - b[seen]).abs().max().item() < 1e-3    # float32 cameras and points
    near, far = with_capture_render(cfg).render.near, with_capture_render(cfg).render.far
    assert 0 < near < 0.5 * radius and far > 2 * radius


def test_a_two_view_point_at_a_camera_does_not_set_the_near_plane(capture, tmp_path):
    # pycolmap's mapper can keep a two-view point triangulated on a camera centre (a lego SfM run did, at
    # 1.7e-7 camera distances in front of it): as the near plane it let the background surfels beside that
    # camera overflow the projection. Depths under STRAY_DEPTH camera distances are passed over.
    (tmp_path / "images").symlink_to(capture / "images", target_is_directory=True)
    rec = pycolmap.Reconstruction(str(capture / "sparse" / "0"))
    ids = sorted(i for i in rec.images if rec.images[i].name in ("im_001.png", "im_002.png"))   # training views
    im = rec.images[ids[0]]
    track = pycolmap.Track()
    for i in ids:
        track.add_element(i, next(k for k, p in enumerate(rec.images[i].points2D) if not p.has_point3D()))
    pid = rec.add_point3D(im.projection_center() + 1e-6 * im.viewing_direction(), track)
    rec.points3D[pid].error = 0.1
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(tmp_path / "sparse" / "0"))
    planted = with_capture_render(load_config(Config, {**_config(capture), "data": {
        **_config(capture)["data"], "root": str(tmp_path)}}))
    prep = prepare(planted)
    _, depth, inside = project(prep.points.xyz, prep.splits["train"])
    assert depth[inside].min().item() < 1e-5                # the planted point is in view, at the camera
    near = with_capture_render(load_config(Config, _config(capture))).render.near
    assert planted.render.near == pytest.approx(near, rel=1e-6)


def test_colmap_config_trains_and_evaluates_the_every_eighth_views(capture, tmp_path):
    cfg_path = tmp_path / "colmap.yaml"
    cfg_path.write_text(yaml.safe_dump(_config(capture)))
    run = tmp_path / "run"
    assert main(["--config", str(cfg_path), "--run", str(run)]) == 0
    m = json.loads((run / "eval_test" / "metrics.json").read_text())
    per_view = json.loads((run / "eval_test" / "per_view.json").read_text())["views"]
    assert m["split"] == "test" and [v["name"] for v in per_view] == ["im_000.png", "im_008.png", "im_016.png"]
    assert sorted(p.name for p in (run / "eval_test").glob("im_000*")) == ["im_000.png", "im_000_gt.png"]
    assert m["resolution"] == [SPEC.resolution // 4] * 2
    # after a few steps the model already explains the photos better than a constant grey (a broken near
    # plane, where the background sphere's points beside a camera covered the image, scored 11-12 dB here)
    test = load_views(load_config(Config, _config(capture)), "test", torch.device("cpu"))
    grey = -10 * math.log10(float(((test.images - 0.5) ** 2).mean()))
    assert m["psnr"]["mean"] > grey
    hist = json.loads((run / "history.json").read_text())["history"]
    assert [r["step"] for r in hist] == [2, 4] and all(math.isfinite(r["val_psnr"]) for r in hist)


def test_colmap_config_errors_name_the_key(capture):
    raw = _config(capture)
    raw["data"]["root"] = None
    with pytest.raises(ConfigError, match="data.root"):
        load_config(Config, raw)
    with pytest.raises(ConfigError, match="geometry.init: sfm needs data.source colmap"):
        load_config(Config, {"task": "neural", "geometry": {"init": "sfm"}})
    with pytest.raises(ConfigError, match="geometry.background.model"):
        load_config(Config, {"task": "neural", "geometry": {"background": {"model": "sphere"}}})
    bad = _config(capture)
    bad["data"]["capture"]["val_every"] = 1
    with pytest.raises(ConfigError, match="data.capture.val_every"):
        load_config(Config, bad)
    bad = _config(capture)
    bad["geometry"]["sfm"].update(fill=100, fill_seen=0.0)
    with pytest.raises(ConfigError, match=r"^geometry\.sfm\.fill_seen: expected a value in \(0, 1\], got 0.0$"):
        load_config(Config, bad)
    bad["geometry"]["sfm"].update(fill_seen=0.5, fill_opacity=1.0)
    with pytest.raises(ConfigError, match=r"^geometry\.sfm\.fill_opacity: expected a value in \(0, 1\), got 1.0$"):
        load_config(Config, bad)


def test_sfm_fill_adds_carved_random_points_to_the_sfm_surfels(capture):
    raw = _config(capture)
    raw["geometry"]["sfm"]["fill"] = 0
    base = load_config(Config, raw)
    train = prepare(base).splits["train"]
    plain = initial_geometry(base, train, seed=0)
    sfm = _sfm_points(base, train, 0)[0]
    # this small capture keeps only 2 SfM points near the centre, so ``points`` boxes all of them (background
    # included): a wide box, of which fewer points pass a looser carve
    for box, n, seen in (("bbox", 400, 0.9), ("points", 100, 0.3)):
        raw = _config(capture)
        raw["geometry"]["sfm"].update(fill=n, fill_box=box, fill_seen=seen)
        filled = initial_geometry(load_config(Config, raw), train, seed=0)
        assert filled.num_points == plain.num_points + n
        extra = filled.means[len(sfm):len(sfm) + n].detach()      # after the SfM surfels, before the sphere
        assert torch.equal(filled.means[:len(sfm)].detach(), plain.means[:len(sfm)].detach())
        _, _, inside = project(extra.double(), train)
        assert bool((inside.double().mean(0) >= seen - 1e-6).all())   # the carve: that share of the views sees each
        lo, hi = (torch.full((3,), -1.5), torch.full((3,), 1.5)) if box == "bbox" else fill_box(sfm, 0.5)
        assert bool(((extra >= lo.float() - 1e-5) & (extra <= hi.float() + 1e-5)).all())
        op = filled.opacities.detach()                             # faint fill, the rest at init_opacity
        assert torch.allclose(op[len(sfm):len(sfm) + n], torch.full((n,), 0.1), atol=1e-5)
        assert torch.allclose(torch.cat([op[:len(sfm)], op[len(sfm) + n:]]), plain.opacities.detach(), atol=1e-6)
        assert torch.allclose(plain.opacities.detach(), torch.full((plain.num_points,), base.geometry.init_opacity),
                              atol=1e-5)
    bad = _config(capture)
    bad["geometry"]["sfm"].update(fill=100, fill_box="bbox")
    bad["geometry"]["bbox"] = [40.0, 40.0, 40.0, 41.0, 41.0, 41.0]   # outside every camera's view
    with pytest.raises(ConfigError, match="^geometry.sfm.fill: only 0 of 100 random points"):
        initial_geometry(load_config(Config, bad), train, seed=0)


def test_missing_mask_is_a_one_line_error_naming_it(capture, tmp_path):
    with pytest.raises(DataError, match=r"nomasks/im_000\.png\.png: mask of image 'im_000.png' not found"):
        load_colmap(capture, holdout_every=0, sparse="sparse_gt/0", masks="nomasks", cache_dir=tmp_path)


def test_without_sfm_points_the_near_plane_comes_from_the_background_sphere(capture):
    raw = _config(capture, init="hull", grid=32)
    raw["data"]["capture"].update(sparse="sparse_gt/0", masks="masks")
    raw["geometry"]["background"].update(radius=SPEC.environment / SPEC.radius, centre=[0.0, 0.0, -0.3])
    cfg = with_capture_render(load_config(Config, raw))
    dist = (camera_centres(prepare(cfg).splits["train"].viewmats.double()) - torch.tensor([0.0, 0.0, -0.3],
                                                                                dtype=torch.float64)).norm(dim=1)
    assert cfg.render.near == pytest.approx(0.5 * (SPEC.environment - float(dist.max())))
    assert cfg.render.far == pytest.approx(2.0 * (SPEC.environment + float(dist.max())))
    raw["geometry"]["background"]["radius"] = 0.5             # inside the camera ring: an error naming the key
    with pytest.raises(ConfigError, match="geometry.background.radius: the sphere"):
        with_capture_render(load_config(Config, raw))


ORBIT = CaptureSpec(resolution=128, views=24, elevation=(-30.0, 30.0))  # a full orbit, below the objects too
#: Largest held-out PSNR difference between a capture and the same capture in a moved SfM world (dB). The
#: training frame is the same up to float32 rounding of the moved model (tests/test_capture_frame.py), so the
#: runs differ only by that rounding's effect on 36 stage-1 steps (measured: under 0.005 dB, both captures).
SAME_PSNR_DB = 0.05


@pytest.fixture(scope="module")
def orbit(tmp_path_factory) -> Path:
    return ensure_capture(ORBIT, tmp_path_factory.mktemp("orbits"))


def _moved(capture: Path, out: Path, seed: int) -> Path:
    """``capture`` with its SfM model moved by a random similarity (rotation, translation up to 20 units, scale
    0.1-10): what another SfM run of the same photos may pick. The photos are linked."""
    rng = np.random.default_rng(seed)
    sim = pycolmap.Sim3d(float(np.exp(rng.uniform(math.log(0.1), math.log(10.0)))),
                         pycolmap.Rotation3d(Rotation.random(random_state=rng).as_matrix()), rng.uniform(-20, 20, 3))
    rec = pycolmap.Reconstruction(str(capture / "sparse" / "0"))
    rec.transform(sim)
    (out / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(out / "sparse" / "0"))
    (out / "images").symlink_to(capture / "images", target_is_directory=True)
    return out


def _stage1_psnr(capture: Path, run: Path, **overrides) -> float:
    """Held-out PSNR of a short stage 1 alone (``neural.steps: 0``) of ``configs/colmap.yaml`` on ``capture``."""
    raw = _config(capture)
    raw["geometry"]["optim"] = {"epochs": 2, "batch": 1, "reposition": {"every": 4}}
    raw["geometry"]["background"]["points"] = 16384    # as shipped: the fixture's 2048 leave holes that stall it
    raw["neural"]["steps"] = 0
    for key, value in overrides.items():
        section, name = key.split("__")
        raw[section][name] = value
    cfg_path = run.with_suffix(".yaml")
    cfg_path.write_text(yaml.safe_dump(raw))
    assert main(["--config", str(cfg_path), "--run", str(run)]) == 0
    return json.loads((run / "eval_test" / "metrics.json").read_text())["psnr"]["mean"]


@pytest.mark.parametrize("which, seed", [("hemisphere", 1), ("orbit", 2)])
def test_training_is_the_same_in_any_sfm_world(which, seed, request, tmp_path):
    """The capture fixture (cameras on a hemisphere) and an orbit (cameras all round, below the objects too),
    each in its SfM world and moved by a random similarity, train to the same held-out PSNR."""
    scene = request.getfixturevalue("capture" if which == "hemisphere" else "orbit")
    ref = _stage1_psnr(scene, tmp_path / "ref")
    test = load_views(load_config(Config, _config(scene)), "test", torch.device("cpu"))
    grey = -10 * math.log10(float(((test.images - 0.5) ** 2).mean()))
    assert ref > grey + 3.0                                  # it learns (measured: 22.2 / 19.1 dB against 14.8 / 15.3)
    moved = _moved(scene, tmp_path / "moved", seed)
    assert abs(_stage1_psnr(moved, tmp_path / "run") - ref) < SAME_PSNR_DB


def test_a_run_that_learns_nothing_stops_and_says_where_the_surfels_are(capture, tmp_path, capsys):
    """A near plane beyond the scene (every surfel clipped): the renders stay the background colour, so stage 1
    stops at its first validation after ``geometry.stall_epochs`` with a one-line error (exit 2)."""
    raw = _config(capture)
    raw["data"]["capture"]["near_far"] = False
    raw["render"] = {**raw.get("render", {}), "near": 50.0, "far": 100.0}
    raw["geometry"].update(optim={"epochs": 8, "batch": 1}, stall_epochs=2)
    raw["geometry"]["log"] = {"every": 18, "checkpoint": 18, "validate": 18}   # 18 training views: an epoch
    cfg_path = tmp_path / "broken.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    assert main(["--config", str(cfg_path), "--run", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "stage 1 learns nothing: after 6.0 epochs the val PSNR is" in err   # the first check: >= 100 steps
    assert re.search(r"a training view sees 9\d% of them \(median\), 0 of 18 views under 1%", err)  # they are in view
    assert "the capture's centre (0.00, 0.00, 0.00) (from the cameras' look-at point; 0 such core" in err
    assert "geometry.stall_epochs: 0 turns this check off" in err
    # the run folder stays (it has checkpoints), with the flat validation curve that stopped it
    history = json.loads((tmp_path / "run" / "geometry_history.json").read_text())["history"]
    assert [h["step"] for h in history] == [18, 36, 54, 72, 90, 108]


def test_initial_surfels_that_no_view_sees_stop_before_training(capture):
    raw = _config(capture, init="random", bbox=[40.0, 40.0, 40.0, 41.0, 41.0, 41.0])
    cfg = load_config(Config, raw)
    with pytest.raises(DataError, match=r"^geometry.init: random: 18 of 18 training views see almost none of the "
                                        r"initial surfels: the 20000 surfels lie about \(40"):
        initial_geometry(cfg, prepare(cfg).splits["train"], seed=0)
