"""Camera paths and videos (:mod:`nsplat.render.camera_paths`, :mod:`nsplat.render.video`): the smooth path passes
through
the training poses and moves smoothly, nerfstudio's ``camera_path.json`` reads to the cameras that wrote it,
depth and normal buffers of a known surfel, the PNG fallback without ffmpeg, and ``render`` end to end
(every path and output) on a tiny neural run."""
from __future__ import annotations

import json
import math
from pathlib import Path

import imageio
import imageio.v3 as iio
import numpy as np
import pytest
import torch
import yaml

from nsplat.cameras import camera_centres, look_at, opengl_c2w_to_viewmat
from nsplat.cli import main
from nsplat.errors import DataError
from nsplat.render.camera_paths import orbit, read_nerfstudio_path, smooth_path, tour
from nsplat.render.renderer import RenderConfig, render_geometry
from nsplat.render.video import depth_picture, normal_picture, write_video
from tests.test_neural import _tiny


def _arc(count: int) -> torch.Tensor:
    """``count`` cameras equally spaced on half a circle of radius 4 at height 1, looking at the origin."""
    ang = torch.linspace(0, math.pi, count, dtype=torch.float64)
    eye = torch.stack([4 * torch.cos(ang), 4 * torch.sin(ang), torch.ones_like(ang)], 1)
    return look_at(eye, torch.zeros_like(eye), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_smooth_path_passes_through_the_training_poses_and_moves_smoothly():
    V = _arc(5)
    shuffled = V[[0, 3, 1, 4, 2]]
    assert tour(camera_centres(shuffled).numpy()) == [0, 2, 4, 1, 3]  # nearest neighbours: back along the arc
    path, knots = smooth_path(shuffled, frames=4 * 8 + 1)  # equal spacing: every 8th frame is a knot
    assert len(knots) == 5
    assert torch.allclose(path[::8], V.float(), atol=1e-5)
    R = path[:, :3, :3].double()
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(33, 3, 3), atol=1e-5)
    steps = camera_centres(path.double()).diff(dim=0).norm(dim=1)
    assert float(steps.max() / steps.min()) < 1.2  # arc-length sampling: even speed
    turn = torch.stack([torch.arccos(((torch.einsum("ij,ij->", a, b) - 1) / 2).clamp(-1, 1))
                        for a, b in zip(R[1:], R[:-1])])
    assert float(turn.max()) < 2 * math.pi / 32  # no jump in orientation
    one, _ = smooth_path(V[:1].expand(3, 4, 4), frames=4)  # a single pose: a still camera
    assert torch.allclose(one, V[:1].float().expand(4, 4, 4))


def test_orbit_circles_the_target_at_the_cameras_distance():
    ang = torch.rand(7, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 * math.pi
    eye = torch.stack([4 * torch.cos(ang), 4 * torch.sin(ang), torch.zeros_like(ang)], 1)
    eye = eye + torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    target = torch.tensor([[1.0, 2.0, 0.5]], dtype=torch.float64).expand(7, 3)
    V = orbit(look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)), frames=12)
    c = camera_centres(V.double()) - target[:1]
    assert torch.allclose(c[:, 2], torch.zeros(12, dtype=torch.float64), atol=1e-4)
    assert torch.allclose(c[:, :2].norm(dim=1), torch.full((12,), 4.0, dtype=torch.float64), atol=1e-4)
    forward = V[:, 2, :3].double()  # every orbit camera looks at the target
    assert torch.allclose((forward * -c).sum(1) / c.norm(dim=1), torch.ones(12, dtype=torch.float64), atol=1e-4)


def _camera_path(path: Path, c2ws: list[np.ndarray], fov: float = 40.0, **extra: object) -> Path:
    meta = {"camera_type": "perspective", "render_width": 40, "render_height": 30, "fps": 12, "seconds": 1,
            "camera_path": [{"camera_to_world": c.reshape(-1).tolist(), "fov": fov, "aspect": 4 / 3} for c in c2ws],
            **extra}
    path.write_text(json.dumps(meta))
    return path


def test_nerfstudio_camera_path_reads_to_the_cameras_that_wrote_it(tmp_path):
    c2ws = [torch.linalg.inv(v).numpy() @ np.diag([1.0, -1.0, -1.0, 1.0]) for v in _arc(3)]  # OpenCV → OpenGL
    p = read_nerfstudio_path(_camera_path(tmp_path / "camera_path.json", c2ws))
    assert (p.width, p.height, p.fps, len(p)) == (40, 30, 12, 3)
    assert torch.allclose(p.viewmats, _arc(3).float(), atol=1e-5)
    assert p.Ks[0, 1, 1].item() == pytest.approx(15 / math.tan(math.radians(20)))
    assert torch.allclose(p.Ks[:, 0, 2], torch.full((3,), 20.0))
    assert torch.allclose(p.Ks[:, 1, 2], torch.full((3,), 15.0))
    small = p.resized(20)
    assert (small.width, small.height) == (20, 15) and torch.allclose(small.Ks[:, :2], p.Ks[:, :2] / 2)
    assert torch.allclose(opengl_c2w_to_viewmat(torch.from_numpy(c2ws[1])).float(), p.viewmats[1], atol=1e-5)
    bad = [c.copy() for c in c2ws]
    bad[1][0, 0] = 3.0
    with pytest.raises(DataError, match=r"frame 1: field 'camera_to_world'.*not a rotation"):
        read_nerfstudio_path(_camera_path(tmp_path / "bad.json", bad))
    with pytest.raises(DataError, match=r"frame 0: field 'fov'"):
        read_nerfstudio_path(_camera_path(tmp_path / "bad.json", c2ws, fov=-1.0))
    with pytest.raises(DataError, match=r"camera_type 'fisheye'"):
        read_nerfstudio_path(_camera_path(tmp_path / "bad.json", c2ws, camera_type="fisheye"))


def test_depth_and_normal_of_a_surfel_facing_the_camera():
    V = look_at(torch.tensor([[0.0, 0.0, -3.0]]), torch.zeros(1, 3), torch.tensor([0.0, -1.0, 0.0]))
    K = torch.tensor([[[40.0, 0.0, 16.5], [0.0, 40.0, 16.5], [0.0, 0.0, 1.0]]])  # surfel centre on pixel (16, 16)
    for sign in (1.0, -1.0):  # two-sided: a normal pointing away is turned to face the camera
        alpha, depth, normal = render_geometry(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, sign]]),
                                               torch.full((1, 2), 0.5), torch.tensor([0.9]), V, K, 32, 32,
                                               RenderConfig(renderer="dense", lowpass=0.0))
        centre = (0, 16, 16)
        assert float(alpha[centre]) == pytest.approx(0.9, abs=1e-3)
        assert float(depth[centre]) == pytest.approx(3.0, abs=1e-4)
        assert torch.allclose(normal[centre], torch.tensor([0.0, 0.0, -1.0]), atol=1e-5)
        pic = normal_picture(normal, alpha)[centre]
        assert tuple(pic) == (round(0.9 * 127.5), round(0.9 * 127.5), round(0.9 * 255))  # (0.5, 0.5, 1) · alpha
    depth_pic = depth_picture(depth, alpha)
    assert depth_pic.shape == (1, 32, 32, 3) and (depth_pic[0, 0, 0] == 0).all()  # empty pixels are black


def test_without_ffmpeg_the_video_is_a_png_sequence(tmp_path, monkeypatch, caplog):
    import imageio_ffmpeg

    def missing() -> str:
        raise RuntimeError("No ffmpeg exe could be found")

    frames = np.random.default_rng(0).integers(0, 256, (3, 9, 7, 3), dtype=np.uint8)
    out = write_video(frames, tmp_path / "orbit.mp4", fps=5)
    assert out == tmp_path / "orbit.mp4" and iio.imread(out, index=0).shape == (10, 8, 3)  # padded to even
    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", missing)
    out = write_video(frames, tmp_path / "orbit.mp4", fps=5)
    assert out == tmp_path / "orbit"
    assert sorted(p.name for p in out.iterdir()) == [f"frame_0000{i}.png" for i in range(3)]
    assert np.array_equal(iio.imread(out / "frame_00001.png"), frames[1])
    assert "no ffmpeg backend" in caplog.text and "PNG frames" in caplog.text


def _frames(path: Path) -> list[np.ndarray]:
    return list(imageio.get_reader(path).iter_data())


def test_render_writes_every_path_and_output(tmp_path, capsys, monkeypatch):
    cfg_path = tmp_path / "tiny.yaml"
    cfg_path.write_text(yaml.safe_dump(_tiny(tmp_path / "cache", steps=2)))
    run = tmp_path / "run"
    assert main(["--config", str(cfg_path), "--run", str(run)]) == 0
    assert main(["render", "--run", str(run), "--path", "test", "--outputs", "rgb,depth,normal,alpha", "--fps", "5",
                 "--resolution", "32"]) == 0
    for name in ("test.mp4", "test_depth.mp4", "test_normal.mp4", "test_alpha.mp4"):
        frames = _frames(run / name)
        assert len(frames) == 2 and frames[0].shape == (32, 32, 3), name  # the 2 test views at 32 px
    assert main(["render", "--run", str(run), "--path", "train-smooth", "--frames", "7"]) == 0
    assert len(_frames(run / "train-smooth.mp4")) == 7
    c2ws = [torch.linalg.inv(v).numpy() @ np.diag([1.0, -1.0, -1.0, 1.0]) for v in _arc(3)]
    _camera_path(tmp_path / "fly.json", c2ws)
    monkeypatch.chdir(tmp_path)  # a relative camera path file is found from the current folder
    assert main(["render", "--run", str(run), "--path", "fly.json", "--outputs", "rgb"]) == 0
    frames = _frames(run / "fly.mp4")
    assert len(frames) == 3 and frames[0].shape == (30, 40, 3)
    out = capsys.readouterr().out
    assert "fly video (rgb, 3 frames, 40x30, 12 fps) written to" in out
    assert main(["render", "--run", str(run), "--outputs", "rgb,colour"]) == 2
    assert main(["eval", "--run", str(run), "--path", "test"]) == 2
