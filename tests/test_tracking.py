"""RGB-D tracking from the frames alone (:mod:`nsplat.data.tracking`, :mod:`nsplat.data.registration`): the model
map merges exactly, one registration recovers a known camera motion on the ray-traced room, a sequence written by
the test is tracked without any trajectory and its path recovered, and a TUM folder without a trajectory runs the
refine task end to end (``trajectory: auto`` estimates it)."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import torch
from kornia.geometry.liegroup import Se3

from nsplat.cameras import intrinsics_from_fov
from nsplat.cli import main
from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.data.fusion import FusionConfig, frame_vertices
from nsplat.data.registration import AlignConfig, PointModel, align, frame_pyramid, intensity
from nsplat.data.tracking import ModelMap, TrackingConfig, track
from nsplat.tasks import refine
from nsplat.tasks.refine.data import load_data
from nsplat.tasks.refine.room import render_frame, room_primitives, trajectory
from nsplat.tasks.refine.trajectory import ate, rotation_angle
from tests.rgbd_scene import write_sequence
from tests.test_refine_rgbd import _config


def _frames(n: int, width: int = 96, height: int = 72) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                               torch.Tensor]:
    """``n`` ray-traced frames of the room along its arc: depths ``[n,H,W]``, images, Ks and true ``c2w``."""
    V = trajectory(n)
    K = intrinsics_from_fov(70.0, width, height)[0]
    prims = room_primitives()
    deps, imgs = [], []
    with torch.no_grad():
        for v in V:
            f = render_frame(prims, v, K.double(), width, height, supersample=1)
            ok = torch.isfinite(f["depth"]) & f["valid"]
            deps.append(torch.where(ok, f["depth"], torch.zeros_like(f["depth"])).float())
            imgs.append(f["image"].float())
    return torch.stack(deps), torch.stack(imgs), K.float().expand(n, 3, 3).clone(), torch.linalg.inv(V.double())


def test_model_map_merges_exactly_and_doubles_its_voxel():
    """Adding points in two parts gives the one-part sums; past the cap the voxel doubles and the weighted mean
    position of everything is unchanged."""
    g = torch.Generator().manual_seed(0)
    p = torch.rand(2000, 3, generator=g, dtype=torch.float64)
    n = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g, dtype=torch.float64), dim=-1)
    v, w = torch.rand(2000, generator=g, dtype=torch.float64), torch.rand(2000, generator=g, dtype=torch.float64) + .1
    one, two = ModelMap(0.05, 10 ** 6), ModelMap(0.05, 10 ** 6)
    one.add(p, n, v, w)
    two.add(p[:700], n[:700], v[:700], w[:700])
    two.add(p[700:], n[700:], v[700:], w[700:])
    assert torch.equal(one.keys, two.keys) and torch.allclose(one.sums, two.sums, rtol=1e-12, atol=1e-12)
    capped = ModelMap(0.05, 1000)
    capped.add(p, n, v, w)
    assert len(capped) <= 1000 and capped.voxel == pytest.approx(0.1)
    mean = (capped.sums[:, 1:4].sum(0) / capped.sums[:, 0].sum())
    assert torch.allclose(mean, (p * w[:, None]).sum(0) / w.sum(), atol=1e-12)


def test_registration_recovers_a_known_motion():
    """A frame registered to the surfels of another lands on its true pose within 1 mm and 0.05°: by geometry
    alone from the other frame's pose (a 14° / 21 cm motion between them, no motion prior), and with the default
    settings (photometric term, exposure, prior) from its true pose moved by 3° and 5 cm."""
    depths, images, Ks, c2w = _frames(12, 160, 120)
    c = frame_vertices(depths[0], Ks[0], FusionConfig())
    R, t = c2w[0, :3, :3].float(), c2w[0, :3, 3].float()
    model = PointModel(c["points"].float() @ R.T + t, c["normals"].float() @ R.T,
                       intensity(images[0]).reshape(-1)[c["index"]])
    moved = torch.linalg.inv(c2w[1]) @ c2w[0]
    assert float(moved[:3, 3].norm()) > 0.15 and math.degrees(float(rotation_angle(moved[:3, :3]))) > 10
    twist = torch.tensor([0.03, -0.03, 0.025, 0.03, 0.03, -0.02], dtype=torch.float64)
    near = Se3.exp(twist[None]).matrix()[0] @ c2w[1]
    for cfg, start in ((AlignConfig(prior_trans=0.0, photometric=0.0), c2w[0]), (AlignConfig(), near)):
        res = align(frame_pyramid(depths[1], images[1], Ks[1], cfg.levels), model, start, cfg)
        E = torch.linalg.inv(c2w[1]) @ res.c2w
        assert res.ok and float(E[:3, 3].norm()) < 1e-3, E
        assert math.degrees(float(rotation_angle(E[:3, :3]))) < 0.05, E


def test_tracking_recovers_the_path_without_a_trajectory():
    """32 frames of the room tracked from the frames alone: the path's ATE is under 2 mm (the room is 3 m across,
    the camera moves about 8 cm / 3-5° a frame) and no frame is lost; the re-alignment rounds do not make it worse."""
    depths, images, Ks, c2w = _frames(32)
    tracked = track(depths, images, Ks, TrackingConfig(rounds=0), progress=False)
    out = track(depths, images, Ks, TrackingConfig(), progress=False)
    assert out.lost == [] and tracked.lost == []
    assert ate(out.c2w, c2w)["rmse"] < 2e-3, ate(out.c2w, c2w)
    assert ate(out.c2w, c2w)["rmse"] <= ate(tracked.c2w, c2w)["rmse"]
    assert torch.allclose(out.c2w[0], torch.eye(4, dtype=torch.float64))


def test_tracking_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="iterations"):
        AlignConfig(levels=2, iterations=[3])
    with pytest.raises(ConfigError, match="predict"):
        TrackingConfig(predict="oracle")  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def frames_only(tmp_path_factory) -> dict[str, object]:
    """A synthetic TUM folder with frames and ground truth only (no trajectory file)."""
    folder = tmp_path_factory.mktemp("tum_frames_only") / "seq"
    info = write_sequence(folder, frames=24, width=96, height=72)
    (folder / "odometry.txt").unlink()
    info["folder"] = folder
    return info


def test_folder_without_trajectory_estimates_it(frames_only, tmp_path):
    """``trajectory: auto`` on a folder with no trajectory file tracks the frames; ``estimate`` does so even when
    the folder has one; the ground truth only scores."""
    cfg = load_config(refine.Config, read_yaml(_config(tmp_path, frames_only)))
    assert cfg.data.rgbd.trajectory == "auto"
    data = load_data(cfg, torch.device("cpu"), progress=False)
    assert data.sequence.source["trajectory"] == "estimate" and data.sequence.source["lost"] == []
    assert ate(data.sequence.c2w, frames_only["c2w"])["rmse"] < 0.01
    with_odo = tmp_path / "with_odometry"
    shutil.copytree(Path(frames_only["folder"]), with_odo)
    (with_odo / "odometry.txt").write_text("# nothing usable\n")
    cfg2 = load_config(refine.Config, read_yaml(_config(tmp_path, {**frames_only, "folder": with_odo},
                                                        **{"data.rgbd.trajectory": "estimate"})))
    assert load_data(cfg2, torch.device("cpu"), progress=False).sequence.source["trajectory"] == "estimate"


def test_frames_only_folder_runs_end_to_end(frames_only, tmp_path, capsys):
    """One command on a folder with only frames and ground truth: tracks, fuses, refines and prints the
    before/after table; metrics.json keeps the estimate's ATE as ``before.ate_rmse`` and says where it came
    from; the estimate is written as a TUM file."""
    run = tmp_path / "run"
    cfg = _config(tmp_path, frames_only, steps=2, **{"heldout.steps": 2})
    assert main(["--config", str(cfg), "--run", str(run)]) == 0
    assert "| ATE RMSE (m) |" in capsys.readouterr().out
    m = json.loads((run / "metrics.json").read_text())
    assert m["before"]["source"]["trajectory"] == "estimate"
    assert m["before"]["ate_rmse"] < 0.01 and "ate_rmse" in m["after"]
    assert (run / "trajectory_estimate.txt").is_file() and (run / "trajectory.txt").is_file()


def test_retrack_repairs_a_drifting_trajectory(tmp_path):
    """``data.rgbd.retrack`` on the room's sequence with an odometry drifting 1° and 3 cm a frame: the
    refinement starts from the re-tracked trajectory (its ATE a fraction of the given one's), "before" still
    scores the trajectory as given, and the files say which is which."""
    folder = tmp_path / "drifting"
    info = write_sequence(folder, frames=16, width=96, height=72, rot_deg=1.0, trans=0.03)
    info["folder"] = folder
    run = tmp_path / "run"
    cfg = _config(tmp_path, info, steps=2, **{"data.rgbd.retrack": True, "data.rgbd.tracking": {"rounds": 1},
                                              "heldout.steps": 2})
    assert main(["--config", str(cfg), "--run", str(run)]) == 0
    m = json.loads((run / "metrics.json").read_text())
    given = ate(info["odometry"], info["c2w"])["rmse"]
    assert m["before"]["ate_rmse"] == pytest.approx(given, rel=1e-4)
    assert m["before"]["start"]["ate_rmse"] < 0.1 * given, m["before"]["start"]
    assert m["after"]["ate_rmse"] < 0.1 * given
    assert m["before"]["source"]["retracked"]["lost"] == []
    assert (run / "trajectory_retracked.txt").is_file() and (run / "trajectory_initial.txt").is_file()
