"""Loaders for a user's own capture: COLMAP sparse models and nerfstudio ``transforms.json``.

Fixtures are made here: a small ``pycolmap.Reconstruction`` (one camera of each supported model with mild
distortion, posed images, SfM points with tracks) written with pycolmap, and photos rendered through each
distorted camera from a smooth pattern over the camera's normalised image plane, so that an undistorted
photo has a known exact value at every pixel.
"""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import pytest
import torch
from scipy.spatial.transform import Rotation

from nsplat.data.capture import heldout_split
from nsplat.data.colmap import load_colmap
from nsplat.data.transforms_json import load_transforms
from nsplat.data.undistort import pinhole_camera, pixel_centres, undistort_points
from nsplat.errors import DataError

W, H, F = 64, 48, 60.0
#: One camera per supported model, mild distortion (barrel and pincushion), off-centre principal points.
MODELS: dict[str, list[float]] = {
    "SIMPLE_PINHOLE": [F, 32.0, 24.0],
    "PINHOLE": [F, F + 2.0, 31.5, 23.5],
    "SIMPLE_RADIAL": [F, 32.0, 24.0, -0.06],
    "RADIAL": [F, 32.5, 23.5, 0.05, -0.02],
    "OPENCV": [F, F + 1.0, 32.5, 24.5, -0.06, 0.015, 0.001, -0.0008],
}
IMAGES = 10
POINTS = 12


def _pattern(xy: np.ndarray) -> np.ndarray:
    """``[N,2]`` normalised image coordinates → ``[N,3]`` colours in [0.1, 0.9], smooth (period ~15 px)."""
    x, y = xy[:, 0] * F, xy[:, 1] * F
    base = 0.5 + 0.2 * np.sin(x / 2.5) * np.cos(y / 3.1)
    return np.stack([base + 0.2 * np.sin((x + y) / 4.0), base, base - 0.2 * np.cos((x - y) / 5.0)], 1)


def _render(camera: pycolmap.Camera) -> np.ndarray:
    """``[H,W,3]`` uint8 photo of the pattern through ``camera`` (distortion included)."""
    rays = camera.cam_from_img(pixel_centres(camera.width, camera.height))
    return np.round(_pattern(rays) * 255).astype(np.uint8).reshape(camera.height, camera.width, 3)


def _exact(K: torch.Tensor, width: int, height: int) -> np.ndarray:
    """``[H,W,3]`` the pattern as an ideal pinhole camera ``K`` sees it."""
    K = K.double().numpy()
    uv = pixel_centres(width, height)
    xy = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]], 1)
    return _pattern(xy).reshape(height, width, 3)


def _camera(camera_id: int, model: str, params: list[float] | None) -> pycolmap.Camera:
    if params is None:
        return pycolmap.Camera.create_from_model_name(camera_id, model, F, W, H)
    return pycolmap.Camera(camera_id=camera_id, model=model, width=W, height=H, params=params)


def _reconstruction(models: dict[str, list[float] | None], seed: int = 0) -> pycolmap.Reconstruction:
    """Cameras ``1..len(models)``; image ``j`` (``im_0j.png``) uses camera ``j % len + 1`` and looks at the
    origin from about 4 units; point ``k`` is observed by the images with ``(j + k) % 3 != 0``."""
    g = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    cameras = [_camera(i + 1, m, p) for i, (m, p) in enumerate(models.items())]
    for cam in cameras:
        rec.add_camera_with_trivial_rig(cam)
    xyz = g.uniform(-0.4, 0.4, (POINTS, 3))
    for j in range(IMAGES):
        cam = cameras[j % len(cameras)]
        R = Rotation.from_rotvec(g.uniform(-0.1, 0.1, 3))
        t = np.array([*g.uniform(-0.1, 0.1, 2), 4.0])
        uv = cam.img_from_cam(R.apply(xyz) + t)
        image = pycolmap.Image(name=f"im_{j:02d}.png", keypoints=uv, camera_id=cam.camera_id, image_id=j + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R.as_quat()), t))
    for k in range(POINTS):
        track = pycolmap.Track()
        for j in range(IMAGES):
            if (j + k) % 3:
                track.add_element(j + 1, k)
        rec.add_point3D(xyz[k], track, g.integers(0, 256, 3).astype(np.uint8))
    rec.update_point_3d_errors()
    return rec


def _write_scene(root: Path, fmt: str = "bin", models: dict[str, list[float] | None] = MODELS
                 ) -> pycolmap.Reconstruction:
    """``root/sparse/0/*.{fmt}`` + ``root/images/im_0j.png`` rendered through each image's camera."""
    rec = _reconstruction(models)
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (rec.write_binary if fmt == "bin" else rec.write_text)(str(model))
    (root / "images").mkdir()
    for image in rec.images.values():
        iio.imwrite(root / "images" / image.name, _render(rec.cameras[image.camera_id]))
    return rec


def _viewmat(image: pycolmap.Image) -> torch.Tensor:
    V = torch.eye(4, dtype=torch.float64)
    V[:3] = torch.from_numpy(image.cam_from_world().matrix())
    return V


def _all(cap):
    """``(names, viewmats, Ks, images)`` of train and test views together."""
    return (cap.train.names + cap.test.names, torch.cat([cap.train.viewmats, cap.test.viewmats]),
            torch.cat([cap.train.Ks, cap.test.Ks]), torch.cat([cap.train.images, cap.test.images]))


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_colmap_model_loads_to_the_cameras_that_wrote_it(tmp_path, fmt):
    rec = _write_scene(tmp_path / "scene", fmt)
    cap = load_colmap(tmp_path / "scene", cache_dir=tmp_path / "cache")
    names, viewmats, Ks, images = _all(cap)
    assert sorted(names) == sorted(im.name for im in rec.images.values())
    assert images.shape == (IMAGES, H, W, 3) and images.dtype == torch.float32
    assert cap.train.masks is None and cap.train.background is None
    for name, V, K in zip(names, viewmats, Ks):
        image = rec.find_image_with_name(name)
        written = rec.cameras[image.camera_id]
        assert torch.allclose(V.double(), _viewmat(image), atol=1e-6, rtol=0)
        assert torch.equal(V[3], torch.tensor([0.0, 0.0, 0.0, 1.0]))
        got = cap.cameras[name]
        assert (got.model_name, got.width, got.height) == (written.model_name, W, H)
        assert np.array_equal(got.params, written.params)
        if written.is_undistorted():  # a pinhole camera keeps its own intrinsics
            fx, fy, cx, cy = written.focal_length_x, written.focal_length_y, written.principal_point_x, \
                written.principal_point_y
            assert torch.equal(K, torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float32))
        else:
            assert torch.allclose(K.double(), torch.from_numpy(pinhole_camera(written).calibration_matrix()))
    pts = cap.points
    ids = sorted(rec.point3D_ids())
    assert len(pts) == POINTS
    assert torch.allclose(pts.xyz.double(), torch.tensor(np.array([rec.points3D[i].xyz for i in ids])), atol=1e-6)
    assert torch.equal(pts.rgb, torch.tensor(np.array([rec.points3D[i].color for i in ids]), dtype=torch.float32) / 255)
    assert pts.track_length.tolist() == [rec.points3D[i].track.length() for i in ids]
    assert pts.track_length.tolist() == [sum(1 for j in range(IMAGES) if (j + k) % 3) for k in range(POINTS)]
    assert bool((pts.error >= 0).all()) and float(pts.error.max()) < 1e-6  # keypoints are exact projections


@pytest.mark.parametrize("model", list(MODELS))
def test_undistortion_agrees_with_pycolmap_projection(tmp_path, model):
    """World points projected by pycolmap's distorted camera, undistorted by our path, land where the
    loaded pinhole view (``Ks``, ``viewmats``) projects them: to 1e-3 px over the whole image."""
    rec = _write_scene(tmp_path / "scene")
    cap = load_colmap(tmp_path / "scene", cache_dir=tmp_path / "cache")
    names, viewmats, Ks, _ = _all(cap)
    image = next(im for im in rec.images.values() if rec.cameras[im.camera_id].model_name == model)
    camera = rec.cameras[image.camera_id]
    g = np.random.default_rng(1)
    uv = np.concatenate([g.uniform([0, 0], [W, H], (300, 2)), [[0, 0], [W, 0], [0, H], [W, H]]])  # corners too
    cam_pts = np.concatenate([camera.cam_from_img(uv), np.ones((len(uv), 1))], 1) * g.uniform(2, 6, (len(uv), 1))
    V = _viewmat(image).numpy()
    world = (cam_pts - V[:3, 3]) @ V[:3, :3]  # Rᵀ (x - t)
    distorted = camera.img_from_cam((world @ V[:3, :3].T) + V[:3, 3])
    ours = undistort_points(distorted, camera, pinhole_camera(camera))
    i = names.index(image.name)
    Kv, Vv = Ks[i].double().numpy(), viewmats[i].double().numpy()
    q = (world @ Vv[:3, :3].T + Vv[:3, 3]) @ Kv.T
    assert np.abs(ours - q[:, :2] / q[:, 2:]).max() < 1e-3


def test_undistorted_photos_match_the_pinhole_rendering_and_are_cached(tmp_path):
    scene = tmp_path / "scene"
    rec = _write_scene(scene)
    cap = load_colmap(scene)
    names, _, Ks, images = _all(cap)
    for name, K, img in zip(names, Ks, images):
        err = (img.double().numpy() - _exact(K, W, H))[2:-2, 2:-2]  # bilinear needs a neighbour inside
        if rec.cameras[rec.find_image_with_name(name).camera_id].is_undistorted():
            assert np.abs(err).max() <= 0.5 / 255 + 1e-6  # read as it is: only the PNG rounding
        else:
            assert np.abs(err).mean() < 1.5 / 255 and np.abs(err).max() < 8 / 255
    cache = scene / "nsplat_undistorted" / "images_1"
    distorted = sorted(im.name for im in rec.images.values() if not rec.cameras[im.camera_id].is_undistorted())
    assert sorted(p.name for p in cache.glob("*.png")) == distorted
    manifest = json.loads((cache / "manifest.json").read_text())
    assert sorted(manifest) == distorted
    assert torch.equal(_all(load_colmap(scene))[3], images)  # second load: from the cache
    # A changed photo is undistorted again.
    changed = distorted[0]
    iio.imwrite(scene / "images" / changed, np.zeros((H, W, 3), np.uint8))
    os.utime(scene / "images" / changed, ns=(1, 1))
    names2, _, _, images2 = _all(load_colmap(scene))
    assert float(images2[names2.index(changed)].abs().max()) == 0.0
    assert json.loads((cache / "manifest.json").read_text())[changed]["mtime_ns"] == 1


def test_downscale_reads_the_images_n_folder_or_shrinks_the_photos(tmp_path):
    scene = tmp_path / "scene"
    rec = _write_scene(scene)
    full = load_colmap(scene, cache_dir=tmp_path / "cache")
    colours = {}
    (scene / "images_2").mkdir()
    for j, image in enumerate(rec.images.values()):
        colours[image.name] = np.array([10 * j, 200 - 10 * j, 77], np.uint8)
        iio.imwrite(scene / "images_2" / image.name, np.broadcast_to(colours[image.name], (H // 2, W // 2, 3)).copy())
    half = load_colmap(scene, downscale=2, cache_dir=tmp_path / "cache")
    names, _, Ks, images = _all(half)
    assert images.shape == (IMAGES, H // 2, W // 2, 3)
    for name, img in zip(names, images):  # these photos, not the full-size ones: a constant stays constant
        assert torch.allclose(img, torch.from_numpy(colours[name] / 255.0).float().expand_as(img), atol=1.01 / 255)
    quarter = load_colmap(scene, downscale=4, cache_dir=tmp_path / "cache")  # no images_4: shrunk here
    names4, _, Ks4, images4 = _all(quarter)
    assert images4.shape == (IMAGES, H // 4, W // 4, 3)
    full_names, _, full_Ks, full_images = _all(full)
    S2, S4 = torch.diag(torch.tensor([0.5, 0.5, 1.0])), torch.diag(torch.tensor([0.25, 0.25, 1.0]))
    for name in ("im_00.png", "im_01.png"):  # the two undistorted cameras: intrinsics scale exactly
        i, i4, f = names.index(name), names4.index(name), full_names.index(name)
        assert torch.allclose(Ks[i], S2 @ full_Ks[f]) and torch.allclose(Ks4[i4], S4 @ full_Ks[f])
        area = torch.nn.functional.avg_pool2d(full_images[f].permute(2, 0, 1), 4).permute(1, 2, 0)
        assert torch.allclose(images4[i4], area, atol=1e-6)
    iio.imwrite(scene / "images_2" / "im_03.png", np.zeros((20, 20, 3), np.uint8))
    with pytest.raises(DataError, match=r"images_2/im_03\.png: image is 20x20"):
        load_colmap(scene, downscale=2, cache_dir=tmp_path / "cache")


def test_every_eighth_image_by_name_is_held_out(tmp_path):
    names = [f"frame_{i:03d}.jpg" for i in range(20)]
    shuffled = [names[i] for i in np.random.default_rng(0).permutation(20)]
    train, test = heldout_split(shuffled)
    assert [shuffled[i] for i in test] == [names[0], names[8], names[16]]
    assert [shuffled[i] for i in train] == [n for k, n in enumerate(names) if k % 8]
    assert heldout_split(shuffled, 0) == (sorted(range(20), key=lambda i: shuffled[i]), [])
    with pytest.raises(ValueError, match="holdout_every"):
        heldout_split(names, -1)
    _write_scene(tmp_path / "scene")
    cap = load_colmap(tmp_path / "scene", cache_dir=tmp_path / "cache")
    assert cap.test.names == ["im_00.png", "im_08.png"]
    assert cap.train.names == [f"im_{j:02d}.png" for j in range(IMAGES) if j % 8]


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_of_several_models_the_one_with_most_images_loads(tmp_path, fmt, caplog):
    """COLMAP's mapper writes one model per connected group of images: ``sparse/0`` may be a 3-image
    fragment and ``sparse/1`` the whole capture. The loader takes the largest and says so; ``sparse=``
    picks another."""
    scene = tmp_path / "scene"
    rec = _write_scene(scene, fmt)
    (scene / "sparse" / "0").rename(scene / "sparse" / "1")
    small = _reconstruction(MODELS)
    for image_id in sorted(small.reg_image_ids())[3:]:
        small.deregister_frame(small.image(image_id).frame_id)
    assert small.num_reg_images() == 3
    (scene / "sparse" / "0").mkdir()
    (small.write_binary if fmt == "bin" else small.write_text)(str(scene / "sparse" / "0"))
    with caplog.at_level(logging.INFO, logger="nsplat.data.colmap"):
        cap = load_colmap(scene, cache_dir=tmp_path / "cache", holdout_every=0)
    assert len(cap.train) == rec.num_reg_images() == IMAGES
    assert "sparse/0 (3 images), sparse/1 (10 images); loading sparse/1" in caplog.text
    assert "data.capture.sparse" in caplog.text
    assert len(load_colmap(scene, sparse="sparse/0", cache_dir=tmp_path / "cache", holdout_every=0).train) == 3


def test_registered_images_without_a_photo_are_skipped_with_one_warning(tmp_path, caplog):
    scene = tmp_path / "scene"
    _write_scene(scene)
    (scene / "images" / "im_03.png").unlink()
    (scene / "images" / "im_08.png").unlink()
    with caplog.at_level(logging.WARNING):
        cap = load_colmap(scene, cache_dir=tmp_path / "cache")
    names = cap.train.names + cap.test.names
    assert len(names) == 8 and "im_03.png" not in names and "im_08.png" not in names
    assert cap.test.names == ["im_00.png"]  # every 8th of the 8 present, by name
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0].getMessage()
    message = warnings[0].getMessage()
    assert str(scene / "sparse/0/images.bin") in message and "2 of the 10 registered images" in message
    assert "images/im_03.png" in message and "training on the 8" in message


def _damage(scene: Path, case: str) -> Path:
    """Damage the written scene as ``case`` says; returns the file the error must name."""
    model = scene / "sparse" / "0"
    kind, _, target = case.partition(" ")
    path = model / target if target.startswith(("cameras", "images.", "points3D", "rigs", "frames")) else None
    if case == "images absent":  # too few left: 5 of the 10 (the split needs 6)
        for j in range(3, 8):
            (scene / "images" / f"im_{j:02d}.png").unlink()
        path = model / "images.bin"
    elif case == "unknown camera model":
        path = model / "cameras.bin"
    elif kind == "missing":
        path.unlink()
    elif kind == "truncated" and path.suffix == ".bin":
        data = path.read_bytes()
        path.write_bytes(data[:int(len(data) * 0.6)])
    elif kind == "truncated":  # a text file cut at a line boundary
        path.write_text("".join(path.read_text().splitlines(True)[:-2]))
    elif kind == "padded":
        path.write_bytes(path.read_bytes() + bytes(5))
    return path


#: case → (format, camera models)
CORRUPTIONS = {
    "missing points3D.bin": ("bin", MODELS),
    "missing frames.bin": ("bin", MODELS),
    "images absent": ("bin", MODELS),
    "unknown camera model": ("bin", {"PINHOLE": MODELS["PINHOLE"], "FISHEYE": None}),
    "truncated cameras.bin": ("bin", MODELS),
    "truncated images.bin": ("bin", MODELS),
    "truncated points3D.bin": ("bin", MODELS),
    "padded rigs.bin": ("bin", MODELS),
    "truncated points3D.txt": ("txt", MODELS),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_corrupt_or_partial_model_is_a_one_line_error_naming_the_file(tmp_path, case):
    fmt, models = CORRUPTIONS[case]
    scene = tmp_path / "scene"
    _write_scene(scene, fmt, models)
    named = str(_damage(scene, case))
    with pytest.raises(DataError) as info:
        load_colmap(scene, cache_dir=tmp_path / "cache")
    message = str(info.value)
    assert named in message and "\n" not in message
    if case == "unknown camera model":
        assert "FISHEYE" in message
    if case == "images absent":
        assert "5 of the 10 registered images" in message and "images/im_03.png" in message
        assert "which leaves 5; at least 6 are needed (one in 8 by name held out for testing" in message


#: nerfstudio's applied_transform of ns-process-data: swap x and y, negate z (a rotation).
APPLIED = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]])
TOP = {"camera_model": "OPENCV", "fl_x": F, "fl_y": F + 1.0, "cx": 32.5, "cy": 24.5, "w": W, "h": H,
       "k1": -0.05, "k2": 0.01, "p1": 0.001, "p2": -0.0005}
#: Per-frame overrides, and the pycolmap camera each frame must become.
OVERRIDES = {2: {"fl_x": 58.0, "cx": 31.0}, 4: {"camera_model": "PINHOLE", "k1": 0, "k2": 0, "p1": 0, "p2": 0},
             5: {"k3": 0.002}, 6: {"k1": 0.04, "fl_y": 59.0}}


def _expected_camera(i: int) -> pycolmap.Camera:
    f = {**TOP, **OVERRIDES.get(i, {})}
    pinhole = [f["fl_x"], f["fl_y"], f["cx"], f["cy"]]
    if f["camera_model"] == "PINHOLE":
        model, params = "PINHOLE", pinhole
    elif f.get("k3"):
        model, params = "FULL_OPENCV", pinhole + [f["k1"], f["k2"], f["p1"], f["p2"], f["k3"], 0.0, 0.0, 0.0]
    else:
        model, params = "OPENCV", pinhole + [f["k1"], f["k2"], f["p1"], f["p2"]]
    return pycolmap.Camera(camera_id=i + 1, model=model, width=W, height=H, params=params)


def _write_transforms(root: Path, frames: int = 9, **extra: object) -> list[np.ndarray]:
    """``root/transforms.json`` with :data:`TOP`, :data:`OVERRIDES` and :data:`APPLIED`, photos in
    ``root/images/``; returns each frame's OpenCV world→camera in the source world."""
    g = np.random.default_rng(3)
    (root / "images").mkdir(parents=True)
    A = np.eye(4)
    A[:3] = APPLIED
    gl = np.diag([1.0, -1.0, -1.0, 1.0])
    entries, viewmats = [], []
    for i in range(frames):
        V = np.eye(4)
        V[:3, :3] = Rotation.from_rotvec(g.uniform(-1, 1, 3)).as_matrix()
        V[:3, 3] = [*g.uniform(-0.2, 0.2, 2), 4.0]
        viewmats.append(V)
        c2w = A @ np.linalg.inv(V) @ gl  # OpenGL camera→world in the file's world
        name = f"images/frame_{i:05d}.png"
        iio.imwrite(root / name, _render(_expected_camera(i)))
        entries.append({"file_path": name, "transform_matrix": c2w.tolist(), **OVERRIDES.get(i, {})})
    (root / "transforms.json").write_text(json.dumps({**TOP, "applied_transform": APPLIED.tolist(),
                                                      "frames": entries[::-1], **extra}))
    return viewmats


def test_transforms_json_round_trips_to_the_expected_cameras(tmp_path):
    scene = tmp_path / "ns"
    source = _write_transforms(scene)
    cap = load_transforms(scene, undo_applied_transform=True, cache_dir=tmp_path / "cache")
    assert cap.test.names == ["images/frame_00000.png", "images/frame_00008.png"] and cap.points is None
    names, viewmats, Ks, images = _all(cap)
    A = np.eye(4)
    A[:3] = APPLIED
    in_file = load_transforms(scene, cache_dir=tmp_path / "cache")
    file_names, file_viewmats = _all(in_file)[:2]
    for name, V, K, img in zip(names, viewmats, Ks, images):
        i = int(name[-9:-4])
        assert torch.allclose(V.double(), torch.from_numpy(source[i]), atol=1e-6, rtol=0)
        V_file = file_viewmats[file_names.index(name)].double()
        assert torch.allclose(V_file, torch.from_numpy(source[i] @ np.linalg.inv(A)), atol=1e-6, rtol=0)
        want, got = _expected_camera(i), cap.cameras[name]
        assert (got.model_name, got.width, got.height) == (want.model_name, W, H)
        assert np.allclose(got.params, want.params, rtol=0, atol=1e-12)
        assert torch.allclose(K.double(), torch.from_numpy(pinhole_camera(want).calibration_matrix()))
        err = (img.double().numpy() - _exact(K, W, H))[2:-2, 2:-2]
        assert np.abs(err).mean() < 1.5 / 255 and np.abs(err).max() < 8 / 255
    assert cap.cameras["images/frame_00004.png"].model_name == "PINHOLE"
    assert torch.equal(Ks[names.index("images/frame_00004.png")],
                       torch.tensor([[F, 0, 32.5], [0, F + 1, 24.5], [0, 0, 1]], dtype=torch.float32))


@pytest.mark.parametrize("change, field", [({"camera_model": "EQUIRECTANGULAR"}, "EQUIRECTANGULAR"),
                                           ({"k4": 0.001}, "'k4'"), ({"fl_x": "wide"}, "'fl_x'"),
                                           ({"camera_model": "OPENCV_FISHEYE"}, "p1 or p2"),
                                           ({"aabb_scale": "big"}, "'aabb_scale'"),
                                           ({"applied_transform": [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]},
                                            "'applied_transform'")])
def test_transforms_json_bad_field_is_a_one_line_error(tmp_path, change, field):
    _write_transforms(tmp_path / "ns", frames=2, **change)
    with pytest.raises(DataError) as info:
        load_transforms(tmp_path / "ns", cache_dir=tmp_path / "cache")
    message = str(info.value)
    assert str(tmp_path / "ns" / "transforms.json") in message and field in message and "\n" not in message


def test_transforms_frames_without_a_photo_are_skipped_with_one_warning(tmp_path, caplog):
    """instant-ngp's demo folders list frames whose photo is not there: the others train, with one warning line."""
    scene = tmp_path / "ns"
    _write_transforms(scene)
    for i in (3, 6):
        (scene / f"images/frame_{i:05d}.png").unlink()
    with caplog.at_level(logging.WARNING):
        cap = load_transforms(scene, cache_dir=tmp_path / "cache")
    names = cap.train.names + cap.test.names
    assert len(names) == 7 and not {"images/frame_00003.png", "images/frame_00006.png"} & set(names)
    assert cap.test.names == ["images/frame_00000.png"]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert str(scene / "transforms.json") in warnings[0] and "2 of the 9 frames" in warnings[0]
    assert "(e.g. images/frame_00006.png)" in warnings[0] and "training on the 7" in warnings[0]  # frames listed 8..0


def test_transforms_with_too_few_photos_left_is_a_one_line_error(tmp_path):
    scene = tmp_path / "ns"
    _write_transforms(scene)
    for i in (1, 2, 3, 4):
        (scene / f"images/frame_{i:05d}.png").unlink()
    with pytest.raises(DataError) as info:
        load_transforms(scene, cache_dir=tmp_path / "cache")
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(scene / "transforms.json"))
    assert "4 of the 9 frames" in message and "which leaves 5; at least 6 are needed" in message
    assert "1 test, 1 validation and 4 training views" in message
    with pytest.raises(DataError, match=r"leaves 5; at least 7 are needed \(one in 4 by name .*: 2 test, 1 val"):
        load_transforms(scene, holdout_every=4, cache_dir=tmp_path / "cache")
    assert len(load_transforms(scene, holdout_every=0, cache_dir=tmp_path / "cache").train) == 5  # no test view


def _write_frames(root: Path, cameras: list[pycolmap.Camera], top: dict, frames: list[dict], **extra: object) -> None:
    """``root/transforms.json`` with ``top`` and per-frame ``frames`` fields; photo ``i`` rendered through
    ``cameras[i]`` (its own size), looking at the origin from about 4 units."""
    g = np.random.default_rng(5)
    (root / "images").mkdir(parents=True)
    entries = []
    for i, (camera, fields) in enumerate(zip(cameras, frames)):
        V = np.eye(4)
        V[:3, :3] = Rotation.from_rotvec(g.uniform(-0.2, 0.2, 3)).as_matrix()
        V[:3, 3] = [*g.uniform(-0.2, 0.2, 2), 4.0]
        iio.imwrite(root / f"images/{i:02d}.png", _render(camera))
        c2w = np.linalg.inv(V) @ np.diag([1.0, -1.0, -1.0, 1.0])
        entries.append({"file_path": f"images/{i:02d}.png", "transform_matrix": c2w.tolist(), **fields})
    (root / "transforms.json").write_text(json.dumps({**top, "frames": entries, **extra}))


def _cam(model: str, w: int, h: int, params: list[float]) -> pycolmap.Camera:
    return pycolmap.Camera(camera_id=1, model=model, width=w, height=h, params=params)


def _check_photos(cap, width: int, height: int) -> None:
    """Every loaded photo is the pattern as its pinhole ``K`` sees it (within the warp's interpolation error)."""
    names, _, Ks, images = _all(cap)
    assert images.shape[1:] == (height, width, 3)
    for K, img in zip(Ks, images):
        err = (img.double().numpy() - _exact(K, width, height))[2:-2, 2:-2]
        assert np.abs(err).mean() < 1.5 / 255 and np.abs(err).max() < 8 / 255


def test_transforms_per_frame_intrinsics_and_distortion(tmp_path):
    """nerfstudio's several-camera files: every intrinsic and distortion field in the frames, none at the top."""
    models = [("OPENCV", [F, F + 1.0, 32.5, 24.5, -0.06, 0.015, 0.001, -0.0008]), ("PINHOLE", [58.0, 59.0, 31.0, 23.0]),
              ("OPENCV", [62.0, 62.0, 33.0, 24.0, 0.04, 0.0, 0.0, 0.0])] * 3
    cameras = [_cam(m, W, H, p) for m, p in models]
    frames = []
    for model, p in models:
        fields = dict(zip(("fl_x", "fl_y", "cx", "cy"), p), w=W, h=H, camera_model=model)
        if model == "OPENCV":
            fields.update(zip(("k1", "k2", "p1", "p2"), p[4:]))
        frames.append(fields)
    _write_frames(tmp_path / "ns", cameras, {}, frames)
    cap = load_transforms(tmp_path / "ns", cache_dir=tmp_path / "cache")
    for i, camera in enumerate(cameras):
        got = cap.cameras[f"images/{i:02d}.png"]
        assert got.model_name == camera.model_name and np.allclose(got.params, camera.params, rtol=0, atol=1e-12)
    _check_photos(cap, W, H)


def test_transforms_portrait_photos(tmp_path):
    """Photos stored portrait (w < h) keep their orientation; a photo stored the other way round is named as such."""
    w, h = 48, 64
    camera = _cam("OPENCV", w, h, [F, F, 24.5, 31.5, -0.05, 0.01, 0.0, 0.0])
    top = {"camera_model": "OPENCV", "fl_x": F, "fl_y": F, "cx": 24.5, "cy": 31.5, "w": w, "h": h, "k1": -0.05,
           "k2": 0.01}
    _write_frames(tmp_path / "ns", [camera] * 8, top, [{}] * 8)
    cap = load_transforms(tmp_path / "ns", cache_dir=tmp_path / "cache")
    assert (cap.train.width, cap.train.height) == (w, h)
    _check_photos(cap, w, h)
    iio.imwrite(tmp_path / "ns" / "images/05.png", np.zeros((w, h, 3), np.uint8))
    with pytest.raises(DataError, match="image is 64x48 but camera 6 .* is 48x64 \\(turned a quarter"):
        load_transforms(tmp_path / "ns", cache_dir=tmp_path / "cache")


def test_transforms_camera_angle_x_alone(tmp_path):
    """instant-ngp's minimal file: only ``camera_angle_x``: fl_x = fl_y from it, the principal point at the centre,
    w and h from the photos."""
    angle = 2 * math.atan(0.5 * W / F)
    _write_frames(tmp_path / "ns", [_cam("PINHOLE", W, H, [F, F, W / 2, H / 2])] * 8, {"camera_angle_x": angle},
                  [{}] * 8)
    cap = load_transforms(tmp_path / "ns", cache_dir=tmp_path / "cache")
    camera = cap.cameras["images/00.png"]
    assert (camera.model_name, camera.width, camera.height) == ("OPENCV", W, H)
    assert np.allclose(camera.params, [F, F, W / 2, H / 2, 0, 0, 0, 0], rtol=0, atol=1e-9)
    assert torch.allclose(cap.train.Ks[0], torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]]))
    _check_photos(cap, W, H)
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps({"camera_angle_y": 2 * math.atan(0.5 * H / 50.0),
                                                                 "frames": meta["frames"]}))
    assert np.allclose(load_transforms(tmp_path / "ns").cameras["images/03.png"].params[:2], [50.0, 50.0])
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps({"frames": meta["frames"]}))
    with pytest.raises(DataError, match="frame 0: no focal length: none of x_fov, fl_x, camera_angle_x"):
        load_transforms(tmp_path / "ns")


def test_transforms_aabb_scale_is_kept_and_fisheye_is_read(tmp_path):
    """instant-ngp's ``aabb_scale`` is kept in the capture's metadata; ``OPENCV_FISHEYE`` (or ``is_fisheye``) is
    pycolmap's fisheye camera with k1..k4, undistorted like the others."""
    params = [F, F, 32.0, 24.0, 0.02, -0.01, 0.005, -0.002]
    fisheye = _cam("OPENCV_FISHEYE", W, H, params)
    top = {"fl_x": F, "fl_y": F, "cx": 32.0, "cy": 24.0, "w": W, "h": H, "k1": 0.02, "k2": -0.01, "k3": 0.005,
           "k4": -0.002}
    for flag in ({"camera_model": "OPENCV_FISHEYE"}, {"is_fisheye": True}):
        root = tmp_path / next(iter(flag))
        _write_frames(root, [fisheye] * 8, {**top, **flag}, [{}] * 8, aabb_scale=16)
        cap = load_transforms(root, cache_dir=tmp_path / "cache")
        assert cap.metadata == {"aabb_scale": 16}
        camera = cap.cameras["images/00.png"]
        assert camera.model_name == "OPENCV_FISHEYE" and np.allclose(camera.params, params, rtol=0, atol=1e-12)
        _check_photos(cap, W, H)
    assert _write_transforms(tmp_path / "plain") and load_transforms(tmp_path / "plain").metadata == {}
