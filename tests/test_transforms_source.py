"""Training on a nerfstudio / instant-ngp ``transforms.json`` folder (``data.source: transforms``,
``configs/transforms.yaml``) on a fixture written here: the procedural scene's photos composited on white as
``images/*.png`` with a PINHOLE ``transforms.json``. ``geometry.init: auto`` starts from the point cloud the
file names in ``ply_file_path`` (moved with the cameras into the training frame), else from the hull of the
masks, else from points triangulated from the photos (tests/test_triangulate.py) or, where these 24-pixel photos of
untextured objects give too few, from random points in the cameras' common view; the config trains a few steps
and evaluates."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import yaml
from plyfile import PlyData, PlyElement

from nsplat.cameras import camera_centres
from nsplat.cli import main
from nsplat.config import load_config, read_yaml
from nsplat.data.procedural import ProceduralSpec, ensure_scene
from nsplat.errors import DataError
from nsplat.tasks.neural.capture import prepare
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.diagnosis import stall_message
from nsplat.tasks.neural.starts import initial_geometry, start_kind

REPO = Path(__file__).resolve().parents[1]
SIZE = 24


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """``scene/transforms.json`` + ``images/`` (RGB on white) + ``masks/images/`` (the alpha) of 10 views."""
    src = ensure_scene(ProceduralSpec(seed=1, resolution=SIZE, views=(6, 2, 2), objects=2),
                       tmp_path_factory.mktemp("procedural"))
    root = tmp_path_factory.mktemp("ns") / "scene"
    (root / "images").mkdir(parents=True)
    (root / "masks" / "images").mkdir(parents=True)
    frames, angle = [], None
    for split in ("train", "val", "test"):
        meta = json.loads((src / f"transforms_{split}.json").read_text())
        angle = meta["camera_angle_x"]
        for f in meta["frames"]:
            rgba = iio.imread(src / f"{f['file_path']}.png").astype(np.float64) / 255
            rgb = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
            name = f"images/{split}_{Path(f['file_path']).name}.png"
            iio.imwrite(root / name, (rgb * 255 + 0.5).astype(np.uint8))
            iio.imwrite(root / "masks" / name, (rgba[..., 3] * 255 + 0.5).astype(np.uint8))
            frames.append({"file_path": name, "transform_matrix": f["transform_matrix"]})
    focal = 0.5 * SIZE / math.tan(0.5 * angle)
    (root / "transforms.json").write_text(json.dumps(
        {"camera_model": "PINHOLE", "fl_x": focal, "fl_y": focal, "cx": SIZE / 2, "cy": SIZE / 2, "w": SIZE,
         "h": SIZE, "frames": frames}))
    return root


def _config(scene: Path, **capture) -> dict:
    raw = read_yaml(REPO / "configs" / "transforms.yaml")
    raw["data"] = {**raw["data"], "root": str(scene), "capture": {**raw["data"]["capture"], **capture}}
    raw["geometry"].update({"grid": 24, "max_points": 400, "optim": {"epochs": 1, "batch": 3}})
    raw["geometry"]["background"]["points"] = 1024
    raw["render"] = {**raw.get("render", {}), "samples": 16}
    raw["neural"].update({"steps": 2, "batch": 2, "features": 4, "unet": {"depth": 2, "width": 8},
                          "gan": {"enabled": False}})
    raw["log"] = {"every": 1, "images": 0, "checkpoint": 2, "validate": 2, "progress": False}
    raw["eval"].update({"draws": 1, "val_views": 1, "sheet_views": 2})
    return raw


def _listing(scene: Path, folder: Path, frames: list[dict]) -> Path:
    """``folder``: ``scene``'s files (linked) with a ``transforms.json`` listing ``frames`` instead."""
    folder.mkdir()
    for entry in scene.iterdir():
        if entry.name != "transforms.json":
            (folder / entry.name).symlink_to(entry)
    meta = json.loads((scene / "transforms.json").read_text())
    (folder / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
    return folder


def test_transforms_config_trains_and_evaluates_from_the_common_view(scene, tmp_path, caplog):
    """The file lists three frames more than the folder has photos (as instant-ngp's fox does): the ten present
    train and evaluate, with one warning."""
    frames = json.loads((scene / "transforms.json").read_text())["frames"]
    absent = [{**frames[i], "file_path": f"images/gone_{i}.png"} for i in range(3)]
    raw = _config(_listing(scene, tmp_path / "scene", frames[:4] + absent + frames[4:]))
    cfg = load_config(Config, raw)
    with caplog.at_level(logging.WARNING):
        prep = prepare(cfg)
    assert cfg.data.source == "transforms" and start_kind(cfg) == "view_fill"
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2 and "3 of the 13 frames" in warnings[0] and "images/gone_0.png" in warnings[0]
    # 24-pixel photos of untextured objects on white: too few points to triangulate, said in one line
    assert "triangulation from the 7 training photos found" in warnings[1] and "common view" in warnings[1]
    assert prep.points is None and prep.note in warnings[1]
    assert [len(prep.splits[k]) for k in ("train", "val", "test")] == [7, 1, 2]  # every 8th by name held out
    assert prep.splits["test"].names == ["images/test_r_0.png", "images/val_r_0.png"]  # sorted: 0 and 8
    train = load_views(cfg, "train", torch.device("cpu"))
    start = initial_geometry(cfg, train, seed=0)
    bg = cfg.geometry.background.points
    assert start.num_points > cfg.geometry.max_points  # the common-view points, then the background sphere
    fill = start.opacities.detach()[:cfg.geometry.max_points]
    stall = stall_message(cfg, start, train, 3.0, 10.0, 9.8, 10.5)  # what a stalled stage 1 would say
    assert "\n" not in stall and prep.note in stall
    assert f"the start was {cfg.geometry.max_points} random points in the training cameras' common view" in stall
    assert torch.allclose(fill, torch.full_like(fill, cfg.geometry.sfm.fill_opacity), atol=1e-5)
    assert start.num_points <= cfg.geometry.max_points + bg
    cfg_path = tmp_path / "transforms.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    run = tmp_path / "run"
    assert main(["--config", str(cfg_path), "--run", str(run)]) == 0
    m = json.loads((run / "eval_test" / "metrics.json").read_text())
    assert m["views"] == 2 and m["resolution"] == [SIZE, SIZE] and math.isfinite(m["psnr"]["mean"])
    grey = -10 * math.log10(float(((prep.splits["test"].images - 0.5) ** 2).mean()))
    assert m["psnr"]["mean"] > grey  # two steps already explain the photos better than a constant grey


def test_auto_start_uses_ply_file_path_moved_with_the_cameras_then_the_masks(scene, tmp_path):
    # a cloud in the file's world: points on a sphere of radius 0.5 about (0.1, 0, 0), coloured red
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    xyz = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True) + [0.1, 0.0, 0.0]
    arr = np.zeros(300, dtype=[(k, "<f4") for k in "xyz"] + [(k, "u1") for k in ("red", "green", "blue")])
    arr["x"], arr["y"], arr["z"], arr["red"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], 255
    with_ply = tmp_path / "scene"
    with_ply.mkdir()
    for entry in scene.iterdir():
        (with_ply / entry.name).symlink_to(entry)
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(with_ply / "sparse_pc.ply"))
    meta = json.loads((scene / "transforms.json").read_text())
    (with_ply / "transforms.json").unlink()
    (with_ply / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "sparse_pc.ply"}))
    cfg = load_config(Config, _config(with_ply))
    assert start_kind(cfg) == "capture_ply"
    prep = prepare(cfg)
    start = initial_geometry(cfg, load_views(cfg, "train", torch.device("cpu")), seed=0)
    pts = start.means.detach()[:300].double()
    want = prep.to_training(torch.from_numpy(xyz)).double()
    assert torch.allclose(pts, want, atol=1e-4)  # the same similarity as the cameras
    radius = float(camera_centres(prep.splits["train"].viewmats.double()).norm(dim=1).median())
    assert radius == pytest.approx(cfg.data.capture.radius, rel=0.2)  # the training frame: cameras about 3.2 out
    assert torch.allclose(start.features.detach()[:300, 0], torch.full((300,), 0.98), atol=1e-5)
    (with_ply / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "missing.ply"}))
    with pytest.raises(DataError, match="ply_file_path.*does not exist"):
        prepare(load_config(Config, _config(with_ply, holdout_every=7)))
    masked = load_config(Config, _config(scene, masks="masks"))
    assert start_kind(masked) == "hull"
    hull = initial_geometry(masked, load_views(masked, "train", torch.device("cpu")), seed=0)
    assert hull.num_points > masked.geometry.background.points // 4


def test_too_few_photos_for_the_split_is_one_line_before_training(scene, tmp_path):
    frames = json.loads((scene / "transforms.json").read_text())["frames"]
    gone = [{**f, "file_path": f"images/gone_{i}.png"} for i, f in enumerate(frames[5:])]
    cfg = load_config(Config, _config(_listing(scene, tmp_path / "few", frames[:5] + gone)))
    with pytest.raises(DataError) as info:
        prepare(cfg)
    message = str(info.value)
    assert "\n" not in message and "5 of the 10 frames" in message and "at least 6 are needed" in message
