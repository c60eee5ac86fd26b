"""Bad input to the commands that follow training (``render``, ``export``) and to the inputs a config names
(``geometry.init: ply``, ``data.source: transforms``, ``eval.protocol``): each exits 2 with one line that names
the file, key or flag and what was expected, before any work starts, and leaves the run folder as it was (a
config that fails leaves no run folder)."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import yaml
from plyfile import PlyData, PlyElement

from nsplat.cli import main
from tests.test_neural import _tiny
from tests.test_transforms_source import _config as _transforms_config
from tests.test_transforms_source import scene  # noqa: F401  (the transforms.json fixture)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """One tiny neural run, trained once; every test here must leave it as it was."""
    root = tmp_path_factory.mktemp("errors")
    cfg = root / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(_tiny(root / "cache", steps=2)))
    assert main(["--config", str(cfg), "--run", str(root / "run")]) == 0
    return root / "run"


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in folder.rglob("*") if p.is_file()}


def _one_line_error(capsys, argv: list[str], *needles: str) -> str:
    assert main(argv) == 2, argv
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


def _path_file(path: Path, frames: list[dict] | None = None, **top: object) -> Path:
    eye = np.eye(4)
    eye[2, 3] = 4.0
    meta = {"camera_type": "perspective", "render_width": 32, "render_height": 24, "fps": 10,
            "camera_path": frames if frames is not None else
            [{"camera_to_world": eye.reshape(-1).tolist(), "fov": 40.0, "aspect": 4 / 3}] * 2}
    meta.update(top)
    path.write_text(json.dumps(meta))
    return path


def _frame(**over: object) -> dict:
    eye = np.eye(4)
    eye[2, 3] = 4.0
    return {"camera_to_world": eye.reshape(-1).tolist(), "fov": 40.0, "aspect": 4 / 3, **over}


@pytest.mark.parametrize("case, needles", [
    ("no_camera_path", ["camera_path"]),
    ("zero_frames", ["non-empty list 'camera_path'"]),
    ("no_matrix", ["frame 0", "camera_to_world"]),
    ("wrong_shape", ["frame 1", "camera_to_world", "12 or 16"]),
    ("nan_matrix", ["frame 0", "camera_to_world", "finite"]),
    ("no_fov", ["frame 0", "'fov'"]),
    ("inf_fov", ["frame 1", "'fov'"]),
    ("no_width", ["render_width"]),
    ("not_json", ["not valid JSON"]),
])
def test_malformed_camera_path_is_refused_before_rendering(run, tmp_path, capsys, case, needles):
    path = tmp_path / "camera_path.json"
    if case == "no_camera_path":
        _path_file(path)
        meta = json.loads(path.read_text())
        del meta["camera_path"]
        path.write_text(json.dumps(meta))
    elif case == "zero_frames":
        _path_file(path, [])
    elif case == "no_matrix":
        _path_file(path, [{"fov": 40.0}])
    elif case == "wrong_shape":
        _path_file(path, [_frame(), _frame(camera_to_world=[1.0, 0.0, 0.0, 1.0, 0.0, 1.0])])
    elif case == "nan_matrix":
        bad = _frame()
        bad["camera_to_world"][3] = float("nan")
        path.write_text(json.dumps({"camera_type": "perspective", "render_width": 32, "render_height": 24,
                                    "camera_path": [bad]}).replace("NaN", "NaN"))
    elif case == "no_fov":
        _path_file(path, [{k: v for k, v in _frame().items() if k != "fov"}])
    elif case == "inf_fov":
        path.write_text(json.dumps({"camera_type": "perspective", "render_width": 32, "render_height": 24,
                                    "camera_path": [_frame(), _frame(fov=float("inf"))]}))
    elif case == "no_width":
        _path_file(path)
        meta = json.loads(path.read_text())
        del meta["render_width"]
        path.write_text(json.dumps(meta))
    elif case == "not_json":
        path.write_text('{"camera_path": [')
    before = _snapshot(run)
    err = _one_line_error(capsys, ["render", "--run", str(run), "--path", str(path)], str(path), *needles)
    assert "Traceback" not in err
    assert _snapshot(run) == before


@pytest.mark.parametrize("argv, needles", [
    (["--outputs", "rgb,colour"], ["--outputs", "unknown output 'colour'", "rgb,depth,normal,alpha"]),
    (["--outputs", ","], ["--outputs", "no output named"]),
    (["--frames", "0"], ["--frames", "0"]),
    (["--frames", "-3"], ["--frames"]),
    (["--resolution", "-32"], ["--resolution", "-32"]),
    (["--resolution", "0"], ["--resolution"]),
    (["--fps", "0"], ["--fps"]),
    (["--fps", "nan"], ["--fps"]),
    (["--fps", "inf"], ["--fps", "finite"]),
    (["--path", "sideways"], ["--path", "'sideways'", "orbit"]),
])
def test_bad_render_options_are_refused_before_rendering(run, capsys, argv, needles):
    before = _snapshot(run)
    _one_line_error(capsys, ["render", "--run", str(run), *argv], *needles)
    assert _snapshot(run) == before


def test_export_unknown_format_and_unwritable_path_are_refused(run, tmp_path, capsys):
    before = _snapshot(run)
    _one_line_error(capsys, ["export", "--run", str(run), "--format", "splat"], "--format", "'splat'", "3dgs")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):  # root writes anywhere: a path below a file can never be written
            (tmp_path / "a_file").write_text("x")
            target = tmp_path / "a_file" / "sub" / "out.ply"
        else:
            target = locked / "out.ply"
        _one_line_error(capsys, ["export", "--run", str(run), "--format", "3dgs", "--out", str(target)],
                        "--out", str(target), "cannot be written")
    finally:
        locked.chmod(0o700)
    _one_line_error(capsys, ["export", "--run", str(run), "--format", "ply", "--out", str(tmp_path)],
                    "--out", "is a folder")
    missing = tmp_path / "no_such_folder" / "point_cloud.ply"
    _one_line_error(capsys, ["export", "--run", str(run), "--format", "3dgs", "--out", str(missing)],
                    "--out", str(missing), "does not exist")
    assert not missing.parent.exists()
    # a folder no file can be created in, whoever runs this: /proc refuses new files even to root
    _one_line_error(capsys, ["export", "--run", str(run), "--format", "3dgs", "--out", "/proc/point_cloud.ply"],
                    "--out", "/proc/point_cloud.ply", "cannot be written")
    _one_line_error(capsys, ["export", "--run", str(run), "--format", "ply", "--antialiased"],
                    "--format ply", "--antialiased")
    _one_line_error(capsys, ["export", "--run", str(run), "--format", "3dgs", "--fit-epochs", "-1"],
                    "--fit-epochs", "-1")
    assert _snapshot(run) == before


def test_export_whose_default_folder_cannot_be_made_is_refused(run, tmp_path, capsys):
    """The default output (RUN/export/…) when RUN/export is a file: refused before any work, naming the path."""
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    (copy / "export").write_text("not a folder")
    _one_line_error(capsys, ["export", "--run", str(copy), "--format", "3dgs"], "export path",
                    str(copy / "export" / "point_cloud.ply"), "is a file, not a folder")


def _ply_config(tmp_path: Path, ply: Path) -> Path:
    raw = _tiny(tmp_path / "cache", steps=2)
    raw["geometry"]["init"] = "ply"
    raw["geometry"]["ply"] = str(ply)
    path = tmp_path / "ply.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def _write_points(path: Path, xyz: np.ndarray) -> None:
    v = np.zeros(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = xyz.T
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))


@pytest.mark.parametrize("case, needles", [
    ("missing", ["geometry.ply", "no PLY file"]),
    ("empty_file", ["not a PLY file"]),
    ("no_points", ["zero vertices"]),
    ("truncated", ["not a readable PLY", "early end-of-file"]),
    ("nan", ["NaN or Inf", "vertex 7"]),
])
def test_bad_init_ply_is_refused_before_training(tmp_path, capsys, case, needles):
    ply = tmp_path / "start.ply"
    rng = np.random.default_rng(0)
    if case == "empty_file":
        ply.write_bytes(b"")
    elif case == "no_points":
        _write_points(ply, np.zeros((0, 3)))
    elif case == "truncated":
        _write_points(ply, rng.uniform(-0.5, 0.5, (200, 3)))
        ply.write_bytes(ply.read_bytes()[:-300])
    elif case == "nan":
        xyz = rng.uniform(-0.5, 0.5, (200, 3))
        xyz[7, 1] = np.nan
        _write_points(ply, xyz)
    run = tmp_path / "run"
    err = _one_line_error(capsys, ["--config", str(_ply_config(tmp_path, ply)), "--run", str(run)], *needles)
    assert str(ply) in err
    assert not run.exists()


def _transforms_case(scene_dir: Path, tmp_path: Path, case: str) -> Path:
    root = tmp_path / "scene"
    shutil.copytree(scene_dir, root)
    meta = json.loads((root / "transforms.json").read_text())
    if case == "missing_image":  # one missing photo trains on the rest (a warning); half of them is too few
        for frame in meta["frames"][:5]:
            (root / frame["file_path"]).unlink()
    elif case == "no_transform":
        del meta["frames"][2]["transform_matrix"]
    elif case == "singular":
        m = np.array(meta["frames"][4]["transform_matrix"])
        m[:3, 2] = 0.0
        meta["frames"][4]["transform_matrix"] = m.tolist()
    elif case == "mixed_sizes":
        name = root / meta["frames"][5]["file_path"]
        img = iio.imread(name)
        iio.imwrite(name, np.concatenate([img, img[:4]], axis=0))
    elif case == "intrinsics":
        meta["w"], meta["h"] = 48, 48
    (root / "transforms.json").write_text(json.dumps(meta))
    raw = _transforms_config(root)
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize("case, needles", [
    ("missing_image", ["transforms.json", "5 of the 10 frames", "at least 6 are needed"]),
    ("no_transform", ["transforms.json", "frame 2", "transform_matrix"]),
    ("singular", ["transforms.json", "frame 4", "transform_matrix", "not a rotation"]),
    ("mixed_sizes", ["train_r_5.png", "image is 24x28", "transforms.json is 24x24"]),
    ("intrinsics", ["image is 24x24", "transforms.json is 48x48"]),
])
def test_bad_transforms_capture_is_refused_before_training(scene, tmp_path, capsys, case, needles):  # noqa: F811
    cfg = _transforms_case(scene, tmp_path, case)
    run = tmp_path / "run"
    err = _one_line_error(capsys, ["--config", str(cfg), "--run", str(run)], *needles)
    assert not run.exists(), err


def test_unknown_eval_protocol_is_refused(tmp_path, capsys):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(_tiny(tmp_path / "cache", steps=2)))
    run = tmp_path / "run"
    _one_line_error(capsys, ["--config", str(cfg), "--run", str(run), "eval.protocol=nerf"],
                    "eval.protocol", "'nerf'", "standard", "nsplat")
    assert not run.exists()
