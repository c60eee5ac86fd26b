"""Issue 14, run and CLI classes 1-3, 8 and 9: a run folder belongs to one run, concurrent runs are
refused, resume never changes a run, and every user error is one line on stderr with exit code 2 (no
traceback), naming the culprit, with nothing pre-existing changed."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml

from nsplat.cli import main as cli_main
from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.run.checkpoint import load_checkpoint, rotate_checkpoints, save_checkpoint
from nsplat.tasks.demo import Config as DemoConfig
from tests.conftest import write_dss_ply

ROOT = Path(__file__).resolve().parents[1]
DEMO = ["--config", str(ROOT / "configs" / "demo.yaml"), "points=60", "resolution=6", "views=1", "render.samples=2"]


def folder_hash(folder: Path) -> str:
    """Hash of every path and file content under ``folder`` (the lock file's pid excluded)."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file() and p.name != ".lock":
            h.update(p.read_bytes())
    return h.hexdigest()


def run_cli(capsys, *args: str) -> tuple[int, str]:
    code = cli_main(list(args))
    return code, capsys.readouterr().err


def one_line_error(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _fixture_data(tmp: Path) -> Path:
    """A data folder with a small synthetic DSS bunny (written once per test folder)."""
    root = tmp / "data"
    if not (root / "dss_pointclouds" / "bunny-8000.ply").exists():
        write_dss_ply(root / "dss_pointclouds" / "bunny-8000.ply")
    return root


def _tiny_reconstruct(tmp: Path, epochs: int = 3, name: str = "tiny.yaml") -> Path:
    cfg = {"task": "reconstruct", "seed": 0,
           "data": {"shape": "bunny", "root": str(_fixture_data(tmp)), "views": 2, "width": 12, "height": 12,
                    "cache_dir": str(tmp / "cache")},
           "init": {"count": 40}, "scene": {"channels": 3, "learn": ["means", "normals", "scales", "features"],
                                           "opacity": 1.0},
           "render": {"renderer": "splat", "samples": 3},
           "optim": {"epochs": epochs, "batch": 2, "reposition": {"enabled": False}},
           "log": {"checkpoint": 1, "validate": 0}, "renders": 0}
    path = tmp / name
    path.write_text(yaml.safe_dump(cfg))
    return path


# ------------------------------------------------------------------- 1. re-running into a finished run
def test_rerun_into_finished_run_is_refused_and_changes_nothing(tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli(capsys, *DEMO, "--run", str(run))[0] == 0
    before = folder_hash(run)
    code, err = run_cli(capsys, *DEMO, "seed=3", "--run", str(run))
    line = one_line_error(err)
    assert code == 2 and str(run) in line and "--resume" in line and "--overwrite" in line
    assert folder_hash(run) == before


def test_overwrite_replaces_the_previous_run(tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli(capsys, *DEMO, "--run", str(run))[0] == 0
    (run / "old-output.txt").write_text("from the previous run")
    assert run_cli(capsys, *DEMO, "seed=3", "--run", str(run), "--overwrite")[0] == 0
    assert not (run / "old-output.txt").exists()
    assert read_yaml(run / "config.yaml")["seed"] == 3


def test_rotation_never_removes_the_current_run_or_latest(tmp_path):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    for step in (50, 60):  # a previous run's higher-step files (e.g. copied in): not this run's past
        torch.save({"x": step}, folder / f"ckpt-{step:08d}.pt")
    for step in (1, 2, 3):
        save_checkpoint(tmp_path, step, {"x": torch.tensor(step)}, keep=2)
    names = sorted(p.name for p in folder.glob("ckpt-*.pt"))
    assert names == ["ckpt-00000002.pt", "ckpt-00000003.pt", "ckpt-00000050.pt", "ckpt-00000060.pt"]
    assert int(load_checkpoint(tmp_path)["x"]) == 3  # latest names an existing file
    (folder / "latest").write_text("ckpt-00000002.pt")  # latest names an older file: it is kept
    assert rotate_checkpoints(folder, 3, keep=1) == []


# ------------------------------------------------------------------------- 2. two processes, one folder
HOLDER = "import sys, time; from nsplat.run.context import RunLock; RunLock(sys.argv[1]).acquire(); " \
         "print('locked', flush=True); time.sleep(60)"


def _env() -> dict[str, str]:
    return dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))


def test_locked_run_folder_is_refused_naming_the_holder_and_stale_lock_is_taken(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(run)], env=_env(), stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = folder_hash(run)
        code, err = run_cli(capsys, *DEMO, "--run", str(run))
        line = one_line_error(err)
        assert code == 2 and str(run) in line and f"process {holder.pid}" in line
        assert folder_hash(run) == before
    finally:
        holder.kill()
        holder.wait()
    # the holder died without cleaning up: its lock file stays, its lock is gone
    assert (run / ".lock").read_text().strip() == str(holder.pid)
    assert run_cli(capsys, *DEMO, "--run", str(run))[0] == 0
    assert (run / "demo.png").is_file()


def test_two_trainings_started_together_one_is_refused(tmp_path):
    """A second training on a folder whose run is in progress exits 2 naming the folder and the holder's pid,
    and leaves the holder's checkpoints intact. The first run is long (thousands of steps) and is stopped by
    the test once the second has answered, so the second always meets a live lock however fast the
    machine is (a short first run could finish before the second process has imported torch)."""
    cfg = _tiny_reconstruct(tmp_path, epochs=5000)
    run = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "train.py"), "--config", str(cfg), "--run", str(run)]
    first = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.time() + 180
        while not (run / "checkpoints" / "latest").is_file() and time.time() < deadline:
            assert first.poll() is None, first.communicate()[0][-3000:]
            time.sleep(0.05)
        assert (run / "checkpoints" / "latest").is_file(), "the first run wrote no checkpoint in time"
        second = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
        assert first.poll() is None, "the first run must still hold the lock while the second starts"
    finally:
        first.terminate()
        first.communicate(timeout=120)
    assert second.returncode == 2, second.stderr[-3000:]
    line = one_line_error(second.stderr)
    assert str(run) in line and f"process {first.pid}" in line
    assert int(load_checkpoint(run)["step"]) >= 1  # the holder's checkpoints survive the refused start


def test_cleanup_removes_only_temporaries_of_dead_processes(tmp_path):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (folder / f".ckpt-00000009.pt.tmp-{dead.pid}").write_bytes(b"partial")
        (folder / f".ckpt-00000009.pt.tmp-{live.pid}").write_bytes(b"in flight")
        save_checkpoint(tmp_path, 1, {"x": torch.tensor(1)})
        assert not (folder / f".ckpt-00000009.pt.tmp-{dead.pid}").exists()
        assert (folder / f".ckpt-00000009.pt.tmp-{live.pid}").read_bytes() == b"in flight"
    finally:
        live.kill()
        live.wait()


# ------------------------------------------------------------------ 3. resume with incompatible overrides
def test_resume_with_a_changed_config_is_refused_before_writing(tmp_path, capsys):
    cfg = _tiny_reconstruct(tmp_path, epochs=2)
    run = tmp_path / "run"
    assert run_cli(capsys, "--config", str(cfg), "--run", str(run))[0] == 0
    before = folder_hash(run)
    code, err = run_cli(capsys, "--resume", "--run", str(run), "init.count=64", "render.samples=5")
    line = one_line_error(err)
    assert code == 2 and "init.count" in line and "render.samples" in line and str(run) in line
    assert folder_hash(run) == before
    assert run_cli(capsys, "--resume", "--run", str(run))[0] == 0  # an unchanged resume still works
    assert run_cli(capsys, "eval", "--run", str(run))[0] == 0
    assert json.loads((run / "metrics.json").read_text())["chamfer"] > 0


def test_resume_of_a_finished_run_says_so_and_changes_nothing(tmp_path, capsys):
    cfg = _tiny_reconstruct(tmp_path, epochs=2)
    run = tmp_path / "run"
    assert run_cli(capsys, "--config", str(cfg), "--run", str(run))[0] == 0
    assert (run / "finished.json").is_file()
    (run / "metrics.json").unlink()  # a resume that evaluated again would write it back
    before = folder_hash(run)
    assert cli_main(["--resume", "--run", str(run)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"run folder: {run}"
    assert out[1].startswith("the run finished on ") and "nothing to resume" in out[1]
    assert folder_hash(run) == before
    (run / "finished.json").unlink()  # an unfinished run (killed after its last checkpoint) still resumes
    assert cli_main(["--resume", "--run", str(run)]) == 0
    assert (run / "metrics.json").is_file() and (run / "finished.json").is_file()


def _interrupt_at_checkpoint(monkeypatch, at_step: int, after_saving: bool) -> None:
    """Make the engine's checkpoint save at ``at_step`` raise ``KeyboardInterrupt`` (Ctrl-C), before or after
    writing."""
    import nsplat.run.engine as engine
    original = engine.save_checkpoint

    def save(run_dir, step, state, *args, **kwargs):
        if step == at_step and not after_saving:
            raise KeyboardInterrupt
        path = original(run_dir, step, state, *args, **kwargs)
        if step == at_step:
            raise KeyboardInterrupt
        return path
    monkeypatch.setattr(engine, "save_checkpoint", save)


def test_ctrl_c_after_a_checkpoint_exits_130_naming_the_resume_command_and_the_run_resumes(tmp_path, capsys,
                                                                                        monkeypatch):
    cfg = _tiny_reconstruct(tmp_path, epochs=3)
    run = tmp_path / "run"
    _interrupt_at_checkpoint(monkeypatch, at_step=2, after_saving=True)
    code, err = run_cli(capsys, "--config", str(cfg), "--run", str(run))
    line = err.splitlines()[-1]  # after the progress bars
    assert code == 130 and "Traceback" not in err
    assert line.startswith("interrupted:") and f"--run {run} --resume" in line
    assert load_checkpoint(run)["step"] == 2 and not (run / "finished.json").exists()
    monkeypatch.undo()
    assert run_cli(capsys, "--resume", "--run", str(run))[0] == 0
    assert (run / "finished.json").is_file() and load_checkpoint(run)["step"] == 3


def test_ctrl_c_before_the_first_checkpoint_exits_130_and_leaves_no_run_folder(tmp_path, capsys, monkeypatch):
    cfg = _tiny_reconstruct(tmp_path, epochs=3)
    _interrupt_at_checkpoint(monkeypatch, at_step=1, after_saving=False)
    code, err = run_cli(capsys, "--config", str(cfg), "--run", str(tmp_path / "run"))
    assert code == 130 and "Traceback" not in err
    assert err.splitlines()[-1] == "interrupted before the first checkpoint: nothing to resume"
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------------- 8. user errors: one line, exit 2, no run
@pytest.mark.parametrize("override,key", [("resolution=0", "resolution"), ("views=0", "views"),
                                          ("points=0", "points"), ("points=-5", "points"),
                                          ("render.eps=.nan", "render.eps"), ("render.samples=0", "render.samples")])
def test_impossible_config_values_exit_2_naming_the_key(tmp_path, capsys, override, key):
    code, err = run_cli(capsys, *DEMO, override, "--run", str(tmp_path / "run"))
    line = one_line_error(err)
    assert code == 2 and line.startswith(f"config error: {key}: expected")
    assert not (tmp_path / "run").exists()


def test_bad_data_file_exits_2_naming_it_and_leaves_no_run_folder(tmp_path, capsys):
    scene = tmp_path / "scene"
    (scene / "train").mkdir(parents=True)
    frame = {"file_path": "./train/r_0", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}
    (scene / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": [frame]}))
    cfg = {"task": "neural", "data": {"source": "nerf_synthetic", "root": str(scene)}}
    (tmp_path / "n.yaml").write_text(yaml.safe_dump(cfg))
    code, err = run_cli(capsys, "--config", str(tmp_path / "n.yaml"), "--run", str(tmp_path / "run"))
    line = one_line_error(err)
    assert code == 2 and "transforms_train.json: frame 0: field 'transform_matrix'" in line and "4x4" in line
    assert not (tmp_path / "run").exists()


def test_binary_config_exits_2_naming_the_file(tmp_path, capsys):
    (tmp_path / "b.yaml").write_bytes(bytes(range(256)) * 4)
    code, err = run_cli(capsys, "--config", str(tmp_path / "b.yaml"), "--run", str(tmp_path / "run"))
    assert code == 2 and str(tmp_path / "b.yaml") in one_line_error(err)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("args,needle", [
    (["evaluate", "--run", "X"], "unknown command 'evaluate'; valid commands: train, eval, render"),
    (["views=0"], "views: expected a value >= 1"),
    (["--config", "BINARY"], "is not UTF-8 text"),
])
def test_user_errors_print_no_traceback_in_a_real_process(tmp_path, args, needle):
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe\x00binary")
    args = [str(tmp_path / "bin.yaml") if a == "BINARY" else a for a in args]
    if "views=0" in args:
        args = [*DEMO, *args]
    r = subprocess.run([sys.executable, str(ROOT / "train.py"), *args, "--run", str(tmp_path / "run")],
                       cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert needle in one_line_error(r.stderr)
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------------------------ 9. config parsing
def test_duplicate_yaml_keys_are_an_error_naming_the_key(tmp_path, capsys):
    (tmp_path / "d.yaml").write_text("task: demo\npoints: 100\nviews: 1\npoints: 200\n")
    code, err = run_cli(capsys, "--config", str(tmp_path / "d.yaml"), "--run", str(tmp_path / "run"))
    assert code == 2 and "duplicate key 'points'" in one_line_error(err)


def test_exponent_floats_are_numbers(tmp_path):
    (tmp_path / "e.yaml").write_text("task: demo\nrender: {eps: 1e-3}\n")
    assert load_config(DemoConfig, read_yaml(tmp_path / "e.yaml")).render.eps == 1e-3
    assert load_config(DemoConfig, {"task": "demo"}, ["render.eps=5E-2"]).render.eps == 0.05
    with pytest.raises(ConfigError, match="render.eps: expected a number"):
        load_config(DemoConfig, {"task": "demo"}, ["render.eps=1e-3x"])


def test_options_may_come_after_overrides(tmp_path, capsys):
    run = tmp_path / "run"
    code, _ = run_cli(capsys, "views=1", "--run", str(run), "render.samples=2", "--config",
                      str(ROOT / "configs" / "demo.yaml"), "points=60", "resolution=6")
    assert code == 0
    saved = read_yaml(run / "config.yaml")
    assert (saved["views"], saved["render"]["samples"], saved["points"]) == (1, 2, 60)


def test_nested_range_errors_carry_the_section_prefix(tmp_path, capsys):
    code, err = run_cli(capsys, "--config", str(_tiny_reconstruct(tmp_path)), "--run", str(tmp_path / "run"),
                        "optim.batch=0")
    assert code == 2 and one_line_error(err) == "config error: optim.batch: expected a value >= 1, got 0"
    with pytest.raises(ConfigError, match=r"^x\.y\.samples: expected a value >= 1, got 0"):
        from nsplat.config import from_dict
        from nsplat.render.renderer import RenderConfig
        from_dict(RenderConfig, {"samples": 0}, prefix="x.y.")
