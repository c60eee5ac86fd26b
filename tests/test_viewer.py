"""Web viewer, live training view and exports (issue 16).

One tiny neural run is trained once per module (``viewer=true``: the live session starts, the hooks
run, the port is released); every test views or exports it. The server binds 127.0.0.1 on a free
port and is always stopped; nothing contacts a non-loopback address.
"""
from __future__ import annotations

import dataclasses
import socket
import types
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from nsplat.cli import main
from nsplat.config import ConfigError
from nsplat.gaussians.export import read_npz, read_ply, surfel_arrays
from nsplat.render.renderer import RenderConfig
from nsplat.viewer import live
from nsplat.viewer.camera import camera_request, pose_from_viewmat, vfov_of, viewmat_from_pose
from nsplat.viewer.config import ViewerConfig, split_viewer_overrides
from nsplat.viewer.model import MODES, RenderSettings, render_display
from nsplat.viewer.runs import load_run
from nsplat.viewer.server import ViewerServer, free_port, preview_settings


def _tiny(cache: Path) -> dict:
    return {
        "task": "neural", "seed": 0,
        "data": {"procedural": {"seed": 1, "resolution": 24, "views": [6, 2, 2], "objects": 2,
                                "cache_dir": str(cache)}},
        "geometry": {"grid": 24, "optim": {"epochs": 1, "batch": 3, "reposition": {"enabled": False}}},
        "render": {"samples": 16},
        "neural": {"steps": 4, "batch": 2, "features": 4, "unet": {"depth": 2, "width": 8},
                   "gan": {"width": 8, "layers": 2}},
        "log": {"every": 1, "images": 0, "checkpoint": 4, "validate": 0, "progress": False},
        "eval": {"images": False},
    }


def _port_is_free(port: int) -> bool:
    """Nothing listens on ``port`` any more (SO_REUSEADDR: a closed connection's TIME_WAIT does not count)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("viewer")
    cfg = root / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(_tiny(root / "cache")))
    port = free_port()
    assert main(["--config", str(cfg), "--run", str(root / "run"), "viewer=true", f"viewer.port={port}"]) == 0
    assert _port_is_free(port), "the live viewer did not release its port"
    return root / "run"


@pytest.fixture(scope="module")
def model(run):
    return load_run(run)


def _browser_camera(viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int):
    """What viser reports for a browser looking through this camera (OpenCV c2w pose, vertical fov)."""
    wxyz, pos = pose_from_viewmat(viewmat)
    return types.SimpleNamespace(wxyz=wxyz, position=pos, fov=vfov_of(K, height), aspect=width / height)


class _FakeClient:
    """Stands in for a viser ClientHandle: a camera and a scene that records background images."""

    def __init__(self, camera, fail: bool = False) -> None:
        self.camera, self.images, self.fail = camera, [], fail
        self.scene = types.SimpleNamespace(set_background_image=self._set)

    def _set(self, image: np.ndarray, **_) -> None:
        if self.fail:
            raise ConnectionError("client went away")
        self.images.append(image)


def test_browser_camera_conversion_round_trips(model):
    V = model.cameras.viewmats
    for i in range(V.shape[0]):
        wxyz, pos = pose_from_viewmat(V[i])
        assert torch.allclose(viewmat_from_pose(wxyz, pos), V[i].double(), atol=1e-6)
    cam = _browser_camera(V[0], model.cameras.Ks[0], 40, 30)
    _, K, w, h = camera_request(cam, 80)
    assert (w, h) == (80, 60)
    assert torch.allclose(K, torch.tensor([[2 * float(model.cameras.Ks[0, 0, 0]), 0, 40], [0, 2 * float(
        model.cameras.Ks[0, 1, 1]), 30], [0, 0, 1]], dtype=torch.float64), rtol=1e-6)


def test_server_serves_page_and_render_request_equals_direct_render(model):
    port = free_port()
    server = ViewerServer(model, ViewerConfig(port=port, resolution=24, render={"samples": 8}), thread=False)
    try:
        with urllib.request.urlopen(server.url, timeout=10) as resp:
            page = resp.read().decode("utf-8", "replace")
        assert resp.status == 200 and "<html" in page.lower() and "viser" in page.lower()
        c = model.cameras
        client = _FakeClient(_browser_camera(c.viewmats[0], c.Ks[0], c.width, c.height))
        # the camera the browser reports: the OpenCV pose round trip is exact only to ~1 float32 ulp (checked
        # in test_browser_camera_conversion_round_trips), so the direct render uses the camera it resolves to
        V, K, width, height = camera_request(client.camera, server.settings.resolution)
        direct = render_display(model, V, K, width, height, server.settings)
        assert server._poll_client(7, client) == 1  # the request path a browser camera message takes
        assert client.images[0].shape == (c.height, c.width, 3)
        np.testing.assert_array_equal(client.images[0], direct)
        assert direct.std() > 0  # the view shows something
        for mode in MODES:  # every display mode through the request path equals the direct render
            s = dataclasses.replace(server.settings, mode=mode)
            np.testing.assert_array_equal(server.render_camera(client.camera, s),
                                          render_display(model, V, K, width, height, s))
    finally:
        server.close()
    assert _port_is_free(port)


def test_progressive_preview_while_moving_then_full_render(model):
    server = ViewerServer(model, ViewerConfig(port=free_port(), resolution=64, render={"samples": 8}), thread=False)
    try:
        c = model.cameras
        client = _FakeClient(_browser_camera(c.viewmats[0], c.Ks[0], c.width, c.height))
        assert server._poll_client(1, client) == 1 and client.images[-1].shape[:2] == (64, 64)
        assert server._poll_client(1, client) == 0  # nothing changed: no render
        client.camera = _browser_camera(c.viewmats[1], c.Ks[1], c.width, c.height)
        assert server._poll_client(1, client) == 1  # moved: preview
        assert client.images[-1].shape[:2] == (preview_settings(server.settings).resolution,) * 2
        server.settle_s = 0.0
        assert server._poll_client(1, client) == 1 and client.images[-1].shape[:2] == (64, 64)  # still: full
        server.set_model(model)  # new model (e.g. a training step): full re-render
        assert server._poll_client(1, client) == 1 and client.images[-1].shape[:2] == (64, 64)
    finally:
        server.close()


def test_live_step_renders_within_budget_and_survives_disconnects(model, monkeypatch):
    lv = live.LiveViewer(ViewerConfig(enabled=True, port=free_port(), budget=1.0, refresh_every=1, resolution=24,
                                      render={"samples": 8}))
    try:
        c = model.cameras
        ok = _FakeClient(_browser_camera(c.viewmats[0], c.Ks[0], c.width, c.height))
        gone = _FakeClient(ok.camera, fail=True)
        monkeypatch.setattr(lv.server.server, "get_clients", lambda: {1: ok, 2: gone})
        lv.step(1, lambda: model)
        np.testing.assert_array_equal(ok.images[-1], render_display(model, c.viewmats[0], c.Ks[0], c.width,
                                                                    c.height, lv.server.settings))
        lv.step(2, lambda: model)
        assert len(ok.images) == 2 and lv.errors == 0  # the failing client never reaches the hook
        lv.cfg.budget = 1e-9  # over budget: no render, however due
        lv.step(3, lambda: model)
        assert len(ok.images) == 2

        def broken():
            raise RuntimeError("boom")

        lv.cfg.budget = 1.0
        for k in range(live.MAX_ERRORS):
            lv.step(10 + k, broken)  # never raises into the training loop
        assert lv.server is None  # switched itself off
        lv.step(20, lambda: model)
    finally:
        lv.close()


def test_viewer_overrides_are_split_from_the_task_overrides():
    rest, cfg = split_viewer_overrides(["neural.steps=3", "viewer=true", "viewer.port=9001", "viewer.budget=0.2",
                                        "viewer.render.samples=8"])
    assert rest == ["neural.steps=3"] and cfg.enabled and cfg.port == 9001 and cfg.budget == 0.2
    assert cfg.render_cfg(RenderConfig(samples=40, lowpass=0.3)) == RenderConfig(samples=8, lowpass=0.3)
    assert not split_viewer_overrides(["a=1"])[1].enabled
    assert split_viewer_overrides(["viewer.port=9002"])[1].enabled
    for bad, key in [("viewer.colour=red", "viewer.colour"), ("viewer.port=x", "viewer.port"),
                     ("viewer=maybe", "viewer.enabled"), ("viewer.render.samples=0", "viewer.render.samples"),
                     ("viewer.render.colour=1", "viewer.render.colour")]:
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            split_viewer_overrides([bad])


def test_the_viewer_starts_from_the_runs_render_settings(model):
    """The panel's m and ε are the run's ``render`` settings unless ``viewer.render`` overrides them."""
    run = dataclasses.replace(model.render_cfg, samples=23, eps=0.03)
    assert RenderSettings.start(run, ViewerConfig()).render == run
    assert RenderSettings.start(run, ViewerConfig(render={"samples": 5})).render == dataclasses.replace(run, samples=5)
    assert RenderSettings.start(run, ViewerConfig(resolution=99)).resolution == 99


def test_export_ply_round_trips(run, model, tmp_path):
    out = tmp_path / "s.ply"
    assert main(["export", "--run", str(run), "--format", "ply", "--out", str(out)]) == 0
    back, want = read_ply(out), surfel_arrays(model)
    for key in ("means", "normals", "scales", "opacities", "features"):
        np.testing.assert_array_equal(back[key].numpy(), want[key])
    np.testing.assert_array_equal(back["colours"].numpy(), np.round(want["colours"] * 255).astype(np.uint8))
    from plyfile import PlyData

    names = PlyData.read(str(out))["vertex"].data.dtype.names
    assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")


def test_export_npz_round_trips(run, model, tmp_path):
    out = tmp_path / "s.npz"
    assert main(["export", "--run", str(run), "--format", "npz", "--out", str(out)]) == 0
    back, want = read_npz(out), surfel_arrays(model)
    for key, value in want.items():
        np.testing.assert_array_equal(back[key].numpy(), value)
    np.testing.assert_array_equal(back["viewmats"].numpy(), model.cameras.viewmats.numpy())
    assert back["features"].shape == (model.num_points, 4)


@pytest.mark.parametrize("argv, message", [
    (["view", "--run", "{tmp}/missing"], "no such run folder"),
    (["export", "--run", "{run}", "--format", "obj"], "unknown format 'obj'"),
    (["export", "--run", "{tmp}"], "required: --format"),
    (["export", "--run", "{tmp}", "--format", "ply"], "no config.yaml"),
])
def test_bad_input_exits_2_with_one_line(run, tmp_path, capsys, argv, message):
    argv = [a.format(tmp=tmp_path, run=run) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_a_run_without_checkpoint_is_refused_in_one_line(run, tmp_path, capsys):
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "config.yaml").write_text((run / "config.yaml").read_text())  # stage 2 configured, never trained
    for argv in (["view", "--run", str(fresh)], ["export", "--run", str(fresh), "--format", "ply"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "no checkpoint yet" in err and len(err.splitlines()) == 1


def test_demo_run_is_viewable(tmp_path):
    cfg = tmp_path / "demo.yaml"
    cfg.write_text(yaml.safe_dump({"task": "demo", "points": 500, "resolution": 24, "views": 2,
                                   "render": {"samples": 8}}))
    assert main(["--config", str(cfg), "--run", str(tmp_path / "run")]) == 0
    m = load_run(tmp_path / "run")
    c = m.cameras
    pic = render_display(m, c.viewmats[0], c.Ks[0], c.width, c.height,
                         RenderSettings.start(m.render_cfg, ViewerConfig(resolution=24, render={"samples": 8})))
    assert pic.shape == (24, 24, 3) and pic.std() > 0


def test_refine_run_is_viewable_live_and_after(tmp_path):
    cfg = tmp_path / "refine.yaml"
    cfg.write_text(yaml.safe_dump({
        "task": "refine", "data": {"cache_dir": str(tmp_path / "cache"), "room": {
            "width": 20, "height": 15, "frames": 3, "supersample": 1, "keyframe_stride": 1, "pixel_stride": 2}},
        "render": {"samples": 8}, "optim": {"steps": 2, "batch": 2},
        "log": {"every": 1, "images": 0, "checkpoint": 2}}))
    port = free_port()
    assert main(["--config", str(cfg), "--run", str(tmp_path / "run"), "viewer=true", f"viewer.port={port}"]) == 0
    assert _port_is_free(port)
    m = load_run(tmp_path / "run")
    c = m.cameras
    assert c.viewmats.shape == (3, 4, 4) and c.images.shape == (3, 15, 20, 3)
    pic = render_display(m, c.viewmats[0], c.Ks[0], c.width, c.height,
                         RenderSettings.start(m.render_cfg, ViewerConfig(resolution=20, render={"samples": 8})))
    assert pic.shape == (15, 20, 3) and pic.std() > 0
