"""Failure behaviour of the framework: corrupt or missing data files and bad configs give clear errors
naming the file or key; a training process killed with SIGKILL during or right after a checkpoint
write resumes from the last complete checkpoint (never from a partial file) and ends bit-identical to
an uninterrupted run."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import yaml

from nsplat.cli import main as cli_main
from nsplat.data.nerf_synthetic import load_split
from nsplat.data.pointclouds import read_oriented_ply
from nsplat.run.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from nsplat.scene import SceneConfig, SurfelScene
from tests.conftest import write_dss_ply

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------ datasets
def _nerf_scene(root: Path, frames: int = 2) -> str:
    (root / "train").mkdir(parents=True)
    fr = []
    for i in range(frames):
        iio.imwrite(root / "train" / f"r_{i}.png", np.full((4, 4, 4), 200, np.uint8))
        fr.append({"file_path": f"./train/r_{i}", "transform_matrix": np.eye(4).tolist()})
    text = json.dumps({"camera_angle_x": 0.7, "frames": fr})
    (root / "transforms_train.json").write_text(text)
    return text


def test_nerf_loader_accepts_the_fixture(tmp_path):
    _nerf_scene(tmp_path)
    assert load_split(tmp_path, "train").images.shape == (2, 4, 4, 3)


def test_nerf_missing_transforms_names_the_file(tmp_path):
    _nerf_scene(tmp_path)
    (tmp_path / "transforms_train.json").unlink()
    with pytest.raises(FileNotFoundError, match="transforms_train.json"):
        load_split(tmp_path, "train")


def test_nerf_truncated_transforms_names_the_file(tmp_path):
    text = _nerf_scene(tmp_path)
    (tmp_path / "transforms_train.json").write_text(text[: len(text) // 2])
    with pytest.raises(ValueError, match=re.escape(str(tmp_path / "transforms_train.json"))):
        load_split(tmp_path, "train")


def test_nerf_frame_without_pose_names_the_file_and_frame(tmp_path):
    _nerf_scene(tmp_path)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    del meta["frames"][1]["transform_matrix"]
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"transforms_train.json: frame 1 .*transform_matrix"):
        load_split(tmp_path, "train")


def test_nerf_missing_image_names_the_image(tmp_path):
    _nerf_scene(tmp_path)
    (tmp_path / "train" / "r_1.png").unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "train" / "r_1.png"))):
        load_split(tmp_path, "train")


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_nerf_corrupt_image_names_the_image(tmp_path, damage):
    _nerf_scene(tmp_path)
    img = tmp_path / "train" / "r_1.png"
    data = img.read_bytes()
    img.write_bytes(data[:30] if damage == "truncated" else b"not a png" * 10)
    with pytest.raises(ValueError, match=re.escape(str(img))):
        load_split(tmp_path, "train")


@pytest.mark.parametrize("damage", ["truncated", "header_only", "garbage"])
def test_corrupt_point_cloud_names_the_file(tmp_path, damage):
    intact = write_dss_ply(tmp_path / "intact.ply")
    data = intact.read_bytes()
    bad = tmp_path / "bunny.ply"
    bad.write_bytes({"truncated": data[: len(data) // 2], "header_only": data[:200],
                     "garbage": b"garbage\n" * 10}[damage])
    assert read_oriented_ply(intact).points.shape[0] > 0  # the intact file reads
    with pytest.raises(ValueError, match=re.escape(str(bad))):
        read_oriented_ply(bad)


def test_missing_point_cloud_and_missing_properties_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "nope.ply"))):
        read_oriented_ply(tmp_path / "nope.ply")
    scene = SurfelScene.from_points(SceneConfig(opacity=None), torch.rand(5, 3), torch.rand(5, 3) + 0.1)
    scene.save_ply(tmp_path / "s.ply")
    with pytest.raises(ValueError, match=r"s\.ply: missing PLY properties \[.f_3., .f_4.\]"):
        SurfelScene.load_ply(tmp_path / "s.ply", SceneConfig(channels=5, opacity=None))
    data = (tmp_path / "s.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[: len(data) - 20])
    with pytest.raises(ValueError, match=re.escape(str(tmp_path / "t.ply"))):
        SurfelScene.load_ply(tmp_path / "t.ply", SceneConfig(opacity=None))


def test_corrupt_checkpoint_is_an_error_naming_the_file(tmp_path):
    save_checkpoint(tmp_path, 3, {"x": torch.arange(5)})
    path = tmp_path / "checkpoints" / "ckpt-00000003.pt"
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match=re.escape(str(path))):
        load_checkpoint(tmp_path)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "elsewhere")


# ------------------------------------------------------------------------------------------- configs
def _train_py(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def test_train_py_unknown_key_in_yaml_exits_2_naming_the_key(tmp_path):
    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    cfg["resolutoin"] = 64  # typo
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(cfg))
    r = _train_py("--config", str(tmp_path / "bad.yaml"), "--run", str(tmp_path / "run"), cwd=tmp_path)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "config error" in r.stderr and "resolutoin" in r.stderr
    assert not (tmp_path / "run").exists()  # nothing was started


def test_train_py_wrong_type_override_exits_2_naming_the_key(tmp_path):
    r = _train_py("--config", str(ROOT / "configs" / "demo.yaml"), "--run", str(tmp_path / "run"), "points=many",
                  cwd=tmp_path)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "points" in r.stderr and "expected an integer" in r.stderr and "'many'" in r.stderr


@pytest.mark.parametrize("config,override,key", [
    ("reconstruct_bunny.yaml", "render.sampels=8", "render.sampels"),       # unknown nested key
    ("reconstruct_bunny.yaml", "render.samples=lots", "render.samples"),    # wrong type, nested
    ("reconstruct_bunny.yaml", "optim.betas=[0.9]", "optim.betas"),          # wrong length
    ("refine_room.yaml", "shading.learn_sh=maybe", "shading.learn_sh"),      # not a bool
    ("refine_room.yaml", "data.room.frames=2.5", "data.room.frames"),         # float for an int
    ("demo.yaml", "eps=[0.1]", "eps"),                                        # list for a number
])
def test_bad_configs_exit_2_naming_the_key(tmp_path, capsys, config, override, key):
    code = cli_main(["--config", str(ROOT / "configs" / config), "--run", str(tmp_path / "run"), override])
    err = capsys.readouterr().err
    assert code == 2
    assert "config error" in err and key in err
    assert not (tmp_path / "run").exists()


def test_missing_and_malformed_config_files(tmp_path, capsys):
    assert cli_main(["--config", str(tmp_path / "none.yaml")]) == 2
    assert "config file not found" in capsys.readouterr().err
    (tmp_path / "m.yaml").write_text("task: demo\npoints: [1, 2\n")
    assert cli_main(["--config", str(tmp_path / "m.yaml")]) == 2
    assert "m.yaml" in capsys.readouterr().err


# ------------------------------------------------------------------------------- SIGKILL and resume
#: Runs train.py in a child that SIGKILLs itself at a chosen point of its ``kill_at``-th checkpoint
#: write: "mid_write" after half of the checkpoint's bytes reached the temporary file, "before_latest"
#: after the checkpoint file is complete and renamed but before the ``latest`` pointer is updated.
KILLER = r'''
import os, signal, sys
import torch
mode, kill_at = sys.argv[1], int(sys.argv[2])
saves = {"n": 0}
real_save, real_replace = torch.save, os.replace
def save(obj, f, *a, **k):
    name = os.path.basename(getattr(f, "name", str(f)))
    if name.startswith(".ckpt-"):
        saves["n"] += 1
        if mode == "mid_write" and saves["n"] == kill_at:
            import io
            buf = io.BytesIO()
            real_save(obj, buf, *a, **k)
            f.write(buf.getvalue()[: len(buf.getvalue()) // 2])
            f.flush()
            os.fsync(f.fileno())
            os.kill(os.getpid(), signal.SIGKILL)
    return real_save(obj, f, *a, **k)
def replace(src, dst, *a, **k):
    if mode == "before_latest" and saves["n"] == kill_at and os.path.basename(str(dst)) == "latest":
        os.kill(os.getpid(), signal.SIGKILL)
    return real_replace(src, dst, *a, **k)
torch.save, os.replace = save, replace
from nsplat.cli import main
sys.exit(main(sys.argv[3:]))
'''

EPOCHS, KILL_AT = 6, 4


def _tiny_config(tmp: Path) -> Path:
    write_dss_ply(tmp / "data" / "dss_pointclouds" / "bunny-8000.ply")  # small synthetic stand-in
    cfg = {"task": "reconstruct", "seed": 0,
           "data": {"shape": "bunny", "root": str(tmp / "data"), "views": 2, "width": 16, "height": 16,
                    "cache_dir": str(tmp / "cache")},
           "init": {"count": 48}, "scene": {"channels": 3, "learn": ["means", "normals", "scales", "features"],
                                           "opacity": 1.0},
           "render": {"renderer": "splat", "samples": 4},
           "optim": {"epochs": EPOCHS, "batch": 2, "reposition": {"enabled": False}},
           "log": {"checkpoint": 1, "validate": 0}, "renders": 0}
    path = tmp / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _popen(args: list[str], cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _scene_state(run: Path, step: int) -> dict[str, torch.Tensor]:
    payload = torch.load(run / "checkpoints" / f"ckpt-{step:08d}.pt", weights_only=False)
    return {**{f"scene.{k}": v for k, v in payload["modules"]["scene"].items()},
            **{f"adam.{i}.{k}": v for i, st in payload["optimizers"]["fit"]["state"].items() for k, v in st.items()
               if isinstance(v, torch.Tensor)}}


def test_sigkill_during_checkpoint_write_resumes_from_last_complete_checkpoint(tmp_path):
    cfg = _tiny_config(tmp_path)
    (tmp_path / "killer.py").write_text(KILLER)
    # GT images once, so that the three runs below do not race to render them
    ref = _popen([str(ROOT / "train.py"), "--config", str(cfg), "--run", str(tmp_path / "ref")], tmp_path)
    assert ref.wait(timeout=300) == 0, ref.stdout.read()[-3000:]
    runs = {mode: tmp_path / mode for mode in ("mid_write", "before_latest")}
    procs = {mode: _popen([str(tmp_path / "killer.py"), mode, str(KILL_AT), "--config", str(cfg), "--run",
                           str(run)], tmp_path) for mode, run in runs.items()}
    for mode, p in procs.items():
        code = p.wait(timeout=300)
        assert code == -9, f"{mode}: expected death by SIGKILL, got {code}: {p.stdout.read()[-3000:]}"
    # state on disk after the kill
    mid = runs["mid_write"] / "checkpoints"
    assert (mid / "latest").read_text() == f"ckpt-{KILL_AT - 1:08d}.pt"
    partial = list(mid.glob(".ckpt-*.tmp-*"))
    assert len(partial) == 1 and partial[0].name.startswith(f".ckpt-{KILL_AT:08d}.pt.tmp-")
    assert not (mid / f"ckpt-{KILL_AT:08d}.pt").exists()
    before = runs["before_latest"] / "checkpoints"
    assert (before / f"ckpt-{KILL_AT:08d}.pt").exists()  # complete, but never announced
    assert (before / "latest").read_text() == f"ckpt-{KILL_AT - 1:08d}.pt"
    # resume both; each must start from the checkpoint `latest` names and finish the schedule
    procs = {mode: _popen([str(ROOT / "train.py"), "--resume", "--run", str(run)], tmp_path)
             for mode, run in runs.items()}
    outputs = {}
    for mode, p in procs.items():
        code = p.wait(timeout=300)
        outputs[mode] = p.stdout.read()
        assert code == 0, f"{mode}: resume failed: {outputs[mode][-3000:]}"
        assert f"resumed at step {KILL_AT - 1}" in outputs[mode], outputs[mode][-3000:]
    assert not list(mid.glob(".ckpt-*.tmp-*")), "the partial temporary was not cleaned up"
    # and end exactly where the uninterrupted run ended
    want = _scene_state(tmp_path / "ref", EPOCHS)
    for mode, run in runs.items():
        got = _scene_state(run, EPOCHS)
        assert want.keys() == got.keys()
        for k in want:
            assert torch.equal(want[k], got[k]), f"{mode}: {k} differs from the uninterrupted run"
