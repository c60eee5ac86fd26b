"""Inputs of an RGB-D refinement that would mislead, caught before any work (issue 74, item 4): a depth scale that
disagrees with the trajectory, a folder without intrinsics, a trajectory that is the ground truth, the raw 65535
reading, an unregistered depth camera (reprojected into the colour camera) and the ATE's Sim(3) alignment."""
from __future__ import annotations

import logging
import re
from pathlib import Path

import imageio.v3 as iio
import pytest
import torch

from nsplat.cli import main
from nsplat.config import ConfigError, load_config, read_yaml
from nsplat.data.depth_checks import check_depth_scale, depth_scale_error, same_trajectory
from nsplat.data.rgbd import Camera, camera_of, depth_to_color_matrix, load_frames, reproject_depth, tum_files
from nsplat.errors import DataError
from nsplat.tasks import refine
from nsplat.tasks.refine.config import RGBDSource
from nsplat.tasks.refine.data import Sequence, load_data
from nsplat.tasks.refine.sequence import trajectory_metrics
from tests.rgbd_scene import write_sequence
from tests.test_command_errors import _one_line_error
from tests.test_refine_rgbd import _config


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> dict[str, object]:
    """A 10-frame synthetic TUM sequence at 128×96 (depth PNGs at 5000 units per metre)."""
    folder = tmp_path_factory.mktemp("tum") / "room_seq"
    info = write_sequence(folder, frames=10, width=128, height=96, rot_deg=1.0, trans=0.02)
    info["folder"] = folder
    return info


def _frames(room: dict[str, object], depth_scale: float, depth_range: tuple[float, float] = (0.1, 50.0)):
    files = tum_files(Path(room["folder"]), "odometry.txt", "groundtruth.txt", 0.02)
    cam = camera_of("", room["intrinsics"], [])
    return files, load_frames(files, cam, depth_scale=depth_scale, depth_range=depth_range, downscale=1,
                              progress=False)


def test_depth_scale_check_finds_the_scale_error(room):
    """Read at the right scale the depth agrees with the trajectory's motion (no error); read at 1000 (5× too deep)
    or 25000 (5× too shallow) the check names the factor and the scale the frames agree with."""
    _, seq = _frames(room, 5000.0)
    best, s_best, s_one = depth_scale_error(seq.depths, seq.Ks, seq.c2w)
    assert 0.8 <= best <= 1.25 and s_one <= 1.1 * s_best
    check_depth_scale(seq.depths, seq.Ks, seq.c2w, 5000.0)
    _, deep = _frames(room, 1000.0)
    with pytest.raises(DataError, match=r"depth_scale: 1000 makes the depth [45]\.?\d?× too deep") as e:
        check_depth_scale(deep.depths, deep.Ks, deep.c2w, 1000.0)
    assert "\n" not in str(e.value)
    _, shallow = _frames(room, 25000.0)
    with pytest.raises(DataError, match="too shallow"):
        check_depth_scale(shallow.depths, shallow.Ks, shallow.c2w, 25000.0)


def test_wrong_depth_scale_exits_2_before_any_work(room, tmp_path, capsys):
    """``data.rgbd.depth_scale: 1000`` on a 5000-units sequence (a median depth that looks plausible): one line,
    exit 2, no run folder."""
    run = tmp_path / "run"
    argv = ["--config", str(_config(tmp_path, room, **{"data.rgbd.depth_scale": 1000.0,
                                                       "data.rgbd.depth_range": [0.1, 50.0]})), "--run", str(run)]
    assert main(argv) == 2
    # the frames' progress bar (cleared on a terminal: leave=False) precedes the one line of the error
    lines = [ln for ln in re.split(r"[\r\n]", capsys.readouterr().err) if ln.strip()]
    assert all(ln.startswith("rgbd frames") for ln in lines[:-1]), lines
    assert lines[-1].startswith("error: data.rgbd.depth_scale: 1000") and "too deep" in lines[-1], lines[-1]
    assert not run.exists()


def test_folder_layout_needs_intrinsics(tmp_path, capsys):
    """The folder layout without an intrinsics file or explicit intrinsics is a config error naming both options
    (no silent Freiburg-1 preset); either one, or the TUM layout with a preset, is fine."""
    with pytest.raises(ConfigError, match=r"data\.rgbd\.intrinsics_file.*data\.rgbd\.intrinsics \[fx, fy, cx, cy\]"):
        load_config(refine.Config, {"data": {"source": "rgbd", "rgbd": {"layout": "folder"}}})
    RGBDSource(layout="folder", intrinsics_file="camera-intrinsics.txt")
    RGBDSource(layout="folder", intrinsics=[500.0, 500.0, 320.0, 240.0])
    RGBDSource(layout="tum", camera="fr2")
    run = tmp_path / "run"
    _one_line_error(capsys, ["--config", "refine_tum.yaml", "data.rgbd.layout=folder", "--run", str(run)],
                    "data.rgbd.intrinsics_file")
    assert not run.exists()


def test_trajectory_identical_to_ground_truth_warns(room, tmp_path, caplog):
    """The ground truth given as the trajectory (even in another world frame) is warned about in one line: its
    ATE measures nothing. The odometry is not."""
    c2w_gt = tum_files(Path(room["folder"]), "groundtruth.txt", "groundtruth.txt", 0.02).c2w_gt
    shift = torch.eye(4, dtype=torch.float64)
    shift[:3, 3] = torch.tensor([1.0, -2.0, 0.5])
    assert same_trajectory(shift @ c2w_gt, c2w_gt)
    assert not same_trajectory(torch.as_tensor(room["odometry"]), c2w_gt)
    cfg = load_config(refine.Config, read_yaml(_config(tmp_path, room, **{"data.rgbd.trajectory": "groundtruth.txt"})))
    with caplog.at_level(logging.WARNING, logger="nsplat"):
        load_data(cfg, torch.device("cpu"), progress=False)
    hits = [r.getMessage() for r in caplog.records if "ground truth itself" in r.getMessage()]
    assert len(hits) == 1 and "\n" not in hits[0] and "measure nothing" in hits[0]


def test_raw_65535_is_invalid_whatever_the_range(room, tmp_path):
    """A saturated / invalid reading (raw 65535) is no depth even when ``depth_range`` would admit 13.1 m."""
    files, _ = _frames(room, 5000.0)
    raw = iio.imread(files.depth[0])
    raw[:10, :20] = 65535
    iio.imwrite(files.depth[0], raw)
    try:
        _, seq = _frames(room, 5000.0, depth_range=(0.1, 100.0))
        assert float(seq.depths[0, :10, :20].abs().max()) == 0.0
        assert bool((seq.depths[0, 20:] > 0).any())
    finally:
        raw[:10, :20] = iio.imread(files.depth[1])[:10, :20]
        iio.imwrite(files.depth[0], raw)


def test_unregistered_depth_is_reprojected_into_the_colour_camera():
    """A depth camera 4 cm to the left of the colour camera (same intrinsics): a fronto-parallel background at 2 m
    and a box at 1 m move by fx·0.04/z pixels (2 and 4), the box occludes the background it slides over (the
    nearest reading wins), and reprojecting back recovers the original."""
    H, W, f = 48, 64, 100.0
    cam = Camera(f, f, 31.0, 23.0)
    depth = torch.full((H, W), 2.0)
    depth[16:32, 20:30] = 1.0
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = 0.04  # depth → colour: points move +x in the colour camera
    out = reproject_depth(depth, cam, cam, T, W, H)
    assert torch.equal(out[16:32, 24:34], torch.full((16, 10), 1.0))  # the box, 4 px right, over the background
    assert float(out[16:32, 22:24].abs().max()) == 0.0  # background it uncovers: no reading lands there
    assert torch.equal(out[16:32, 34:], torch.full((16, W - 34), 2.0))
    assert torch.equal(out[:16, 2:], torch.full((16, W - 2), 2.0))  # the background, 2 px right
    assert float(out[:, :2].abs().max()) == 0.0  # nothing lands left of the shifted background
    back = reproject_depth(out, cam, cam, torch.linalg.inv(T), W, H)
    assert torch.equal(back[16:32, 20:30], depth[16:32, 20:30])
    assert torch.equal(back[:16, :W - 2], depth[:16, :W - 2])
    T12 = depth_to_color_matrix(T[:3].flatten().tolist())
    assert torch.equal(T12, T)
    with pytest.raises(DataError, match="rigid"):
        depth_to_color_matrix([2.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0])
    with pytest.raises(ConfigError, match="depth_to_color"):
        load_config(refine.Config, {"data": {"rgbd": {"depth_to_color": [1.0] * 12}}})


def test_unregistered_depth_through_load_frames(room, tmp_path):
    """``load_frames`` with a depth camera at the colour camera's pose and intrinsics changes nothing; 5 cm to the
    side it moves every reading by fx·0.05/z pixels (the background's shift measured against the registered
    frame's, as a cross-correlation of valid masks would find it)."""
    files, ref = _frames(room, 5000.0)
    cam = camera_of("", room["intrinsics"], [])
    same = load_frames(files, cam, depth_scale=5000.0, depth_range=(0.1, 50.0), downscale=1, progress=False,
                       depth_camera=cam, depth_to_color=None)
    assert torch.allclose(same.depths, ref.depths, atol=1e-6)
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = 0.05
    moved = load_frames(files, cam, depth_scale=5000.0, depth_range=(0.1, 50.0), downscale=1, progress=False,
                        depth_camera=cam, depth_to_color=T)
    d, m = ref.depths[0], moved.depths[0]
    v, u = torch.nonzero(d > 0, as_tuple=True)
    shift = torch.round(cam.fx * 0.05 / d[v, u]).long()
    ok = (u + shift < d.shape[1]) & (m[v, (u + shift).clamp(max=d.shape[1] - 1)] > 0)
    agree = (m[v[ok], (u + shift)[ok]] - d[v[ok], u[ok]]).abs() <= 1e-3 * d[v[ok], u[ok]]
    assert float(agree.double().mean()) > 0.9


def test_sim3_alignment_scores_a_scaled_trajectory():
    """``trajectory_alignment: sim3``: a trajectory at half the ground truth's scale has no ATE after the Sim(3)
    alignment (scale 2 found) and no RPE; ``se3`` reports its error."""
    g = torch.Generator().manual_seed(0)
    gt = torch.eye(4, dtype=torch.float64).repeat(12, 1, 1)
    gt[:, :3, 3] = torch.cumsum(torch.randn(12, 3, generator=g, dtype=torch.float64) * 0.1, 0)
    est = gt.clone()
    est[:, :3, 3] *= 0.5
    seq = Sequence(torch.arange(12, dtype=torch.float64), est, gt, list(range(12)), [])
    se3, sim3 = trajectory_metrics(est, seq, "se3"), trajectory_metrics(est, seq, "sim3")
    assert se3["ate_rmse"] > 0.01 and se3["ate_scale"] == 1.0
    assert sim3["ate_rmse"] < 1e-9 and sim3["ate_scale"] == pytest.approx(2.0) and sim3["rpe_trans_rmse"] < 1e-9
    assert load_config(refine.Config, {"data": {"rgbd": {"trajectory_alignment": "sim3"}}})
    with pytest.raises(ConfigError, match="trajectory_alignment"):
        load_config(refine.Config, {"data": {"rgbd": {"trajectory_alignment": "umeyama"}}})
