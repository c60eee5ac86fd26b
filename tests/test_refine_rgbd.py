"""Task ``refine`` on an RGB-D sequence (``data.source: rgbd``): a small end-to-end refinement of a synthetic TUM
sequence (the room ray-traced, a drifting odometry) lowers the trajectory error and writes what the user gets;
bad input exits 2 with one line before any work; the config on the real capture parses."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from plyfile import PlyData, PlyElement

from nsplat.cli import main
from nsplat.config import load_config, read_yaml
from nsplat.data.paths import config_dir
from nsplat.data.tum_format import read_trajectory
from nsplat.scene import SceneConfig, SurfelScene
from nsplat.tasks import refine
from nsplat.tasks.refine.data import load_data
from nsplat.tasks.refine.exposure import Exposure
from nsplat.tasks.refine.trajectory import ate
from tests.rgbd_scene import write_sequence
from tests.test_command_errors import _one_line_error


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> dict[str, object]:
    """A 10-frame synthetic TUM sequence at 128×96 with a drifting odometry (1° and 2 cm of error a frame)."""
    folder = tmp_path_factory.mktemp("tum") / "room_seq"
    info = write_sequence(folder, frames=10, width=128, height=96, rot_deg=1.0, trans=0.02)
    info["folder"] = folder
    return info


def _config(tmp: Path, seq: dict[str, object], steps: int = 100, **over: object) -> Path:
    """A small refine_tum config on the synthetic sequence, written to ``tmp``: the shipped recipe less the
    smooth-motion prior (the synthetic cameras jump along an arc, they do not move like a hand-held camera) and
    less the re-tracking (tests/test_tracking.py runs it), so the refinement starts from the odometry."""
    raw = read_yaml(config_dir() / "refine_tum.yaml")
    rg = raw["data"]["rgbd"]
    rg.update(root=str(seq["folder"]), intrinsics=seq["intrinsics"], distortion=[], downscale=1, holdout_every=5,
              depth_range=[0.1, 8.0], retrack=False)
    rg["fusion"] = {"voxel": 0.03, "max_points": 20000, "scale_factor": 0.6}  # ~13k surfels
    raw["render"]["samples"] = 8
    raw["optim"]["steps"] = steps
    raw["optim"]["decay_every"] = 0
    raw["poses"]["motion_weight"] = 0.0
    raw["heldout"].update(steps=15, decay_every=0)
    raw["filter"]["enabled"] = False
    raw["log"] = {"every": 5, "images": 0, "validate": 0, "checkpoint": 10}
    for key, value in over.items():
        node = raw
        *path, last = key.split(".")
        for p in path:
            node = node[p]
        node[last] = value
    out = tmp / "cfg.yaml"
    out.write_text(yaml.safe_dump(raw))
    return out


def test_refinement_lowers_the_trajectory_error(sequence, tmp_path, capsys):
    """Refining poses, points, albedo, SH and exposure with the depth term lowers ATE against the ground truth
    (and the odometry's own ATE is what "before" reports); the run writes the refined TUM trajectory (every frame,
    the held-out ones fitted), the PLY, the before/after sheets and videos, metrics.json and the stdout table."""
    torch.manual_seed(0)
    run = tmp_path / "run"
    assert main(["--config", str(_config(tmp_path, sequence, depth_loss=1.0)), "--run", str(run)]) == 0
    out = capsys.readouterr().out
    assert "| ATE RMSE (m) |" in out and "| held-out SSIM |" in out
    m = json.loads((run / "metrics.json").read_text())
    odo_ate = ate(sequence["odometry"], sequence["c2w"])["rmse"]
    assert m["before"]["ate_rmse"] == pytest.approx(odo_ate, rel=1e-5)  # cameras are float32 viewmats
    assert m["after"]["ate_rmse"] < 0.9 * m["before"]["ate_rmse"], m
    assert m["after"]["rpe_trans_rmse"] < m["before"]["rpe_trans_rmse"], m
    # the fair protocol (heldout.fit_before, the default): both sides' held-out cameras fitted the same way
    assert "both sides scored after the same per-frame camera + exposure fit" in out
    assert m["after"]["heldout"]["psnr"] > m["before"]["heldout"]["psnr"] + 0.5, m
    assert m["after"]["heldout"]["psnr"] > m["before"]["heldout_unfitted"]["psnr"] + 1.0, m
    assert m["frames"] == {"train": 8, "heldout": 2} and m["resolution"] == [128, 96]
    stamps, traj = read_trajectory(run / "trajectory.txt")
    assert traj.shape == (10, 4, 4)
    assert ate(traj, sequence["c2w"])["rmse"] == pytest.approx(m["after"]["ate_rmse"], rel=1e-4)
    for name in ("scene.ply", "trajectory_initial.txt", "before_after/train_before.png",
                 "before_after/heldout_after.png"):
        assert (run / name).is_file(), name
    assert (run / "before_after/train.mp4").exists() or (run / "before_after/train").is_dir()
    assert m["wall_s"] > 0 and m["cpu_s"] > 0 and m["peak_rss_gb"] > 0


def test_exposure_anchor_and_only_what_is_asked(sequence, tmp_path):
    """Exposure and the held-out split exist only when the config asks; frame 0's exposure is fixed (its gain
    and bias get no gradient), the others' are learned."""
    cfg = load_config(refine.Config, read_yaml(_config(tmp_path, sequence)))
    data = load_data(cfg, torch.device("cpu"), progress=False)
    assert len(data.frames) == 8 and len(data.heldout) == 2 and data.sequence.heldout == [0, 5]
    model = refine.build(cfg, data.scene, data.frames).modules["model"]
    assert isinstance(model.exposure, Exposure)
    img = torch.rand(2, 4, 4, 3)
    out = model.exposure(img, torch.tensor([0, 1]))
    (out * torch.randn_like(out)).sum().backward()
    assert float(model.exposure.log_gain.grad[0].abs().sum()) == 0.0
    assert float(model.exposure.log_gain.grad[1].abs().sum()) > 0.0
    cfg2 = load_config(refine.Config, read_yaml(_config(tmp_path, sequence, **{"exposure.learn": False,
                                                                               "data.rgbd.holdout_every": 0})))
    data2 = load_data(cfg2, torch.device("cpu"), progress=False)
    assert data2.heldout is None and len(data2.frames) == 10
    model2 = refine.build(cfg2, data2.scene, data2.frames).modules["model"]
    assert model2.exposure is None and not any("exposure" in n for n, _ in model2.named_parameters())


def test_slam_cloud_ply(sequence, tmp_path):
    """``data.rgbd.cloud`` reads a SLAM system's surfel PLY (positions, normals, colours, radii) instead of fusing."""
    n = 50
    rng = np.random.default_rng(0)
    arr = np.zeros(n, dtype=[(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz", "radius")] +
                   [(k, "u1") for k in ("red", "green", "blue")])
    for k in "xyz":
        arr[k] = rng.uniform(0, 3, n)
    arr["nz"], arr["radius"], arr["red"] = 1.0, 0.02, 255
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "slam.ply"))
    cfg = load_config(refine.Config, read_yaml(_config(tmp_path, sequence,
                                                       **{"data.rgbd.cloud": str(tmp_path / "slam.ply")})))
    scene = load_data(cfg, torch.device("cpu"), progress=False).scene
    assert isinstance(scene, SurfelScene) and scene.num_points == n
    assert torch.allclose(scene.scales, torch.full((n, 2), 0.6 * 0.02))
    assert torch.allclose(scene.features[:, 0], torch.ones(n))


def test_bad_input_one_line_exit_2(sequence, tmp_path, capsys):
    """Missing frames, a trajectory covering too few frames, no pairs within the tolerance, an implausible depth
    scale and a PLY without positions: exit 2, one line naming the file or setting, no run folder left."""
    src = Path(sequence["folder"])
    run = tmp_path / "run"

    def cfg(**over: object) -> str:
        return str(_config(tmp_path, sequence, **over))

    broken = tmp_path / "missing_frame"
    broken.mkdir()
    for name in ("rgb.txt", "depth.txt", "odometry.txt", "groundtruth.txt"):
        (broken / name).write_text((src / name).read_text())
    _one_line_error(capsys, ["--config", cfg(**{"data.rgbd.root": str(broken)}), "--run", str(run)],
                    "missing colour frame")
    short = tmp_path / "short.txt"
    short.write_text("\n".join((src / "odometry.txt").read_text().splitlines()[:4]) + "\n")
    _one_line_error(capsys, ["--config", cfg(**{"data.rgbd.trajectory": str(short)}), "--run", str(run)],
              "covers 2 of 10", "need at least 3")
    _one_line_error(capsys, ["--config", cfg(**{"data.rgbd.max_dt": 0.001}), "--run", str(run)], "max_dt")
    _one_line_error(capsys, ["--config", cfg(**{"data.rgbd.depth_scale": 5.0}), "--run", str(run)], "depth_scale")
    arr = np.zeros(3, dtype=[("a", "f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "nopos.ply"))
    _one_line_error(capsys, ["--config", cfg(**{"data.rgbd.cloud": str(tmp_path / "nopos.ply")}), "--run", str(run)],
              "nopos.ply", "x y z")
    assert not run.exists()


def test_shipped_config_parses():
    """configs/refine_tum.yaml loads, asks for what it uses (exposure, SH, the anchor frame) and no more."""
    cfg = load_config(refine.Config, read_yaml(config_dir() / "refine_tum.yaml"))
    assert cfg.data.source == "rgbd" and cfg.exposure.learn and cfg.poses.frozen == [0]
    assert cfg.scene == SceneConfig(channels=3, learn=["means", "normals", "scales", "opacities", "features"],
                                    opacity=None, scale=None)


def _viewmats_of_centres(centres: torch.Tensor) -> torch.Tensor:
    """World → camera ``[B,4,4]`` (float64) of cameras with rotations that vary and optical centres ``centres``."""
    from kornia.geometry.liegroup import So3

    R = So3.exp(torch.linspace(0, 1, centres.shape[0], dtype=torch.float64)[:, None] *
                torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)).matrix().detach()
    V = torch.eye(4, dtype=torch.float64).repeat(centres.shape[0], 1, 1)
    V[:, :3, :3] = R
    V[:, :3, 3] = -(R @ centres[..., None])[..., 0]
    return V


def test_motion_prior_is_zero_for_constant_velocity_at_absolute_stamps():
    """The smooth-motion prior vanishes for centres moving at constant velocity (uneven, absolute TUM-like stamps,
    any rotations) and equals (‖a‖/σ)² for a known acceleration."""
    from nsplat.tasks.refine.poses import motion_prior

    t = 1305031229.0 + torch.tensor([0.0, 0.033, 0.1, 0.133, 0.2], dtype=torch.float64)
    vel = torch.tensor([0.1, -0.05, 0.02], dtype=torch.float64)
    c = (t - t[0])[:, None] * vel
    assert float(motion_prior(_viewmats_of_centres(c), t, 0.5)) < 1e-18
    acc = torch.tensor([0.4, 0.0, 0.0], dtype=torch.float64)
    c2 = c + 0.5 * ((t - t[0]) ** 2)[:, None] * acc
    assert float(motion_prior(_viewmats_of_centres(c2), t, 0.5)) == pytest.approx((0.4 / 0.5) ** 2, rel=1e-6)


def test_odometry_prior_and_mean_rigid():
    """Equal corrections cost nothing; one camera's extra 1 cm costs (1 cm/σ_t)² over its two neighbour pairs;
    the mean of two rigid transforms is rigid and between them."""
    from kornia.geometry.liegroup import Se3

    from nsplat.tasks.refine.poses import odometry_prior
    from nsplat.tasks.refine.sequence import mean_rigid

    D = Se3.exp(torch.tensor([[0.01, 0.0, 0.0, 0.0, 0.02, 0.0]], dtype=torch.float64)).matrix().detach().repeat(4, 1, 1)
    assert float(odometry_prior(D, [0.005, 0.01])) == 0.0
    D2 = D.clone()
    D2[1, 0, 3] += 0.01
    assert float(odometry_prior(D2, [0.005, 0.01])) == pytest.approx(2 * (0.01 / 0.005) ** 2 / 3, rel=1e-9)
    A = Se3.exp(torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.2]], dtype=torch.float64)).matrix().detach()[0]
    B = Se3.exp(torch.tensor([[0.2, 0.0, 0.0, 0.0, 0.0, 0.4]], dtype=torch.float64)).matrix().detach()[0]
    M = mean_rigid(torch.stack([A, B]))
    R = M[:3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert float(torch.atan2(R[1, 0], R[0, 0])) == pytest.approx(0.3, abs=1e-12)
    assert torch.allclose(M[:3, 3], 0.5 * (A[:3, 3] + B[:3, 3]))
