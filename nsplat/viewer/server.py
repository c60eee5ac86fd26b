"""The viser web server: every browser camera rendered by the model through the op.

:class:`ViewerServer` owns a ``viser.ViserServer`` (page, websocket, GUI), the training cameras as
frusta, and a per-client progressive renderer (:meth:`ViewerServer.poll`): a cheap render (a
quarter of the resolution, at most 4 samples) while the camera moves and a full render once it has
been still for :attr:`ViewerServer.settle_s`. :meth:`ViewerServer.render_camera` is the one render
request path (a browser camera + settings → picture); the tests call it directly.

Standalone (``train.py view``) a background thread calls :meth:`poll`; during training the
live-view hook (:mod:`nsplat.viewer.live`) calls it from the training thread between steps.
"""
from __future__ import annotations

import dataclasses
import logging
import socket
import threading
import time

import numpy as np
import torch

from nsplat.render.view_model import ViewModel
from nsplat.viewer.camera import CameraLike, camera_request, pose_from_viewmat, vfov_of
from nsplat.viewer.config import ViewerConfig
from nsplat.viewer.model import MODES, RenderSettings, render_display

log = logging.getLogger(__name__)
EPS_CHOICES = ("0.001", "0.003", "0.01", "0.03", "0.1", "0.3")
_FRUSTUM_IMAGE_SIDE = 64


@dataclasses.dataclass
class _ClientState:
    key: tuple | None = None
    version: int = -1
    full: bool = True
    changed_at: float = 0.0


def _camera_key(camera: CameraLike) -> tuple:
    return (tuple(np.round(np.asarray(camera.wxyz, float), 6)), tuple(np.round(np.asarray(camera.position, float), 6)),
            round(float(camera.fov), 6), round(float(camera.aspect), 4))


#: Samples per pixel of the cheap render while a camera moves (at most; fewer when the panel asks for fewer).
PREVIEW_SAMPLES = 4


def preview_settings(settings: RenderSettings) -> RenderSettings:
    """The cheap settings used while the camera moves: 1/4 resolution (>= 64 px), <= :data:`PREVIEW_SAMPLES`."""
    return dataclasses.replace(settings.with_samples(min(PREVIEW_SAMPLES, settings.render.samples)),
                               resolution=max(64, settings.resolution // 4))


class ViewerServer:
    """A viser server showing ``model``.

    Args:
        model: the scene (replace it later with :meth:`set_model`, e.g. while training).
        cfg: the viewer's settings (``host``, ``port``: where to listen, local only by default; port 0 is not
            supported by viser, pick a free one with :func:`free_port`). The panel starts from the first model's
            render settings with ``cfg.render`` applied (:meth:`RenderSettings.start`) and changes them.
        thread: start a background thread that renders for the connected browsers.
    """

    settle_s: float = 0.15
    #: the first browser camera looks from the first training camera's direction, this many times farther
    #: from the points' centroid (so the frusta around the scene are in view)
    initial_pullback: float = 1.4

    def __init__(self, model: ViewModel | None, cfg: ViewerConfig, thread: bool = True) -> None:
        import viser  # the web server's dependency tree is loaded only when a viewer starts

        self.cfg = cfg
        self.settings: RenderSettings | None = None
        self.progressive = True
        self.last_render_s = 0.0
        self.total_render_s = 0.0
        self._lock = threading.RLock()
        self._version = 0
        self._clients: dict[int, _ClientState] = {}
        self._frusta: list = []
        self._cameras_key: tuple | None = None
        self._stop = threading.Event()
        self.server = viser.ViserServer(host=cfg.host, port=cfg.port, label="nsplat", verbose=False)
        self.host, self.port = cfg.host, self.server.get_port()
        self.model: ViewModel | None = None
        try:
            if model is not None:
                self.set_model(model)
        except BaseException:
            self.server.stop()
            raise
        self._thread = threading.Thread(target=self._loop, name="nsplat-viewer", daemon=True) if thread else None
        if self._thread is not None:
            self._thread.start()

    # ------------------------------------------------------------------ GUI
    def _build_gui(self, s: RenderSettings) -> None:
        gui = self.server.gui
        with gui.add_folder("Render"):
            self._mode = gui.add_dropdown("Show", MODES, initial_value=s.mode,
                                          hint="RGB, splatted features (first 3 channels), alpha or depth")
            self._res = gui.add_slider("Resolution", 16, max(1024, s.resolution), 16, s.resolution,
                                       hint="longest image side (px)")
            self._samples = gui.add_slider("Samples / px", 1, max(64, s.render.samples), 1, s.render.samples,
                                           hint="per-pixel sample size m")
            eps = min(EPS_CHOICES, key=lambda e: abs(float(e) - s.render.eps))
            self._eps = gui.add_dropdown("ε", EPS_CHOICES, initial_value=eps, hint="sampler error bound")
            self._prog = gui.add_checkbox("Progressive", True, hint="cheap render while the camera moves")
            self._cams = gui.add_checkbox("Training cameras", True)
        self._stats = gui.add_markdown("")
        for handle in (self._mode, self._res, self._samples, self._eps, self._prog):
            handle.on_update(lambda _: self._settings_changed())
        self._cams.on_update(lambda _: self._toggle_frusta())

    def _settings_changed(self) -> None:
        with self._lock:
            self.settings = dataclasses.replace(self.settings.with_samples(int(self._samples.value),
                                                                           float(self._eps.value)),
                                                mode=self._mode.value, resolution=int(self._res.value))
            self.progressive = bool(self._prog.value)
            self._version += 1

    def _toggle_frusta(self) -> None:
        for f in self._frusta:
            f.visible = bool(self._cams.value)

    def _show_cameras(self, model: ViewModel) -> None:
        """Frusta with thumbnails for the training cameras (poses updated in place when only they
        changed); the first time also the up direction and the initial browser camera (the first
        training camera's direction, :attr:`initial_pullback` times farther, looking at the points' centroid)."""
        cams = model.cameras
        if cams is None:
            return
        key = (cams.viewmats.data_ptr(), tuple(cams.viewmats.shape), cams.viewmats._version)
        if key == self._cameras_key:
            return
        first = self._cameras_key is None
        self._cameras_key = key
        V = cams.viewmats.detach().double().cpu()
        poses = [pose_from_viewmat(V[i]) for i in range(V.shape[0])]
        if len(self._frusta) == V.shape[0]:
            for f, (wxyz, pos) in zip(self._frusta, poses):
                f.wxyz, f.position = wxyz, pos
            return
        for f in self._frusta:
            f.remove()
        self._frusta = []
        centre = model.means.detach().double().mean(0).cpu()
        eyes = torch.stack([torch.as_tensor(p) for _, p in poses])
        scale = 0.08 * float((eyes - centre).norm(dim=-1).median())
        thumbs = None
        if cams.images is not None:
            step = max(1, max(cams.width, cams.height) // _FRUSTUM_IMAGE_SIDE)
            thumbs = (cams.images[:, ::step, ::step, :3].detach().float().cpu().clamp(0, 1).numpy() * 255
                      ).astype(np.uint8)
        for i, (wxyz, pos) in enumerate(poses):
            self._frusta.append(self.server.scene.add_camera_frustum(
                f"/training_cameras/{i:04d}", fov=vfov_of(cams.Ks[i], cams.height), aspect=cams.width / cams.height,
                scale=scale, thickness=0.05 * scale, color=(60, 90, 200),
                image=None if thumbs is None else thumbs[i], format="jpeg", wxyz=wxyz, position=pos,
                visible=bool(self._cams.value)))
        if first:
            up = -V[:, 1, :3].mean(0)
            up = up / up.norm().clamp_min(1e-12)
            self.server.scene.set_up_direction(tuple(float(x) for x in up))
            eye = centre + self.initial_pullback * (torch.as_tensor(poses[0][1]) - centre)
            self.server.initial_camera.position = tuple(float(x) for x in eye)
            self.server.initial_camera.look_at = tuple(float(x) for x in centre)
            self.server.initial_camera.up = tuple(float(x) for x in up)
            self.server.initial_camera.fov = vfov_of(cams.Ks[0], cams.height)

    # ------------------------------------------------------------------ rendering
    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://{self.host}:{self.port}/"

    def set_model(self, model: ViewModel, refresh: bool = True) -> None:
        """Show ``model`` from now on; ``refresh``: every client re-renders at full quality (otherwise
        only clients whose camera moves do)."""
        with self._lock:
            if self.settings is None:  # the first model: the panel starts from its render settings
                self.settings = RenderSettings.start(model.render_cfg, self.cfg)
                self._build_gui(self.settings)
            self.model = model
            if refresh:
                self._version += 1
        self._show_cameras(model)

    def render_camera(self, camera: CameraLike, settings: RenderSettings | None = None) -> np.ndarray:
        """The render request: ``[H,W,3]`` uint8 picture of ``camera`` (a browser camera) in ``settings``
        (default: the current GUI settings), with the longest side ``settings.resolution``."""
        with self._lock:
            model, settings = self.model, settings or self.settings
        viewmat, K, width, height = camera_request(camera, settings.resolution)
        t0 = time.perf_counter()
        pic = render_display(model, viewmat, K, width, height, settings)
        self.last_render_s = time.perf_counter() - t0
        self.total_render_s += self.last_render_s
        return pic

    def poll(self) -> int:
        """One progressive pass over the connected browsers; returns the number of renders sent.

        Per client: camera moved → preview render (if progressive); still for ``settle_s`` after a
        preview, or the model/settings changed → full render. A client that vanishes mid-way is skipped.
        """
        sent = 0
        clients = self.server.get_clients()
        for gone in set(self._clients) - set(clients):
            self._clients.pop(gone, None)
        for cid, client in clients.items():
            try:
                sent += self._poll_client(cid, client)
            except Exception as exc:  # noqa: BLE001 - a disconnecting browser must not stop the viewer
                log.debug("viewer: client %s skipped: %s", cid, exc)
        return sent

    def _due(self, cid: int, client, commit: bool) -> RenderSettings | None:
        """Settings of the render ``client`` needs now, or ``None``; ``commit`` records it as done."""
        cam = client.camera
        if getattr(cam, "_state", None) is not None and cam._state.update_timestamp == 0.0:
            return None  # the browser has not reported its camera yet
        key, now = _camera_key(cam), time.perf_counter()
        st = self._clients.get(cid) or _ClientState()
        with self._lock:
            version, settings, progressive = self._version, self.settings, self.progressive
        if key != st.key:
            moving = st.key is not None and progressive
            use = preview_settings(settings) if moving else settings
            update = dict(key=key, changed_at=now, full=not moving)
        elif not st.full and now - st.changed_at >= self.settle_s:
            use, update = settings, dict(full=True)
        elif st.version != version:
            use, update = settings, {}
        else:
            return None
        if commit:
            self._clients[cid] = dataclasses.replace(st, version=version, **update)
        return use

    def pending(self) -> bool:
        """Whether some connected browser needs a render now (its camera moved, or it waits for the
        full-quality render after a preview, or the model/settings changed)."""
        try:
            return any(self._due(cid, c, commit=False) is not None for cid, c in self.server.get_clients().items())
        except Exception:  # noqa: BLE001 - a client vanishing mid-check
            return False

    def _poll_client(self, cid: int, client) -> int:
        if self.model is None:
            return 0
        use = self._due(cid, client, commit=True)
        if use is None:
            return 0
        pic = self.render_camera(client.camera, use)
        client.scene.set_background_image(pic, format="jpeg", jpeg_quality=90)
        self._stats.content = (f"**{self.model.task or 'scene'}** · {self.model.num_points:,} points  \n"
                               f"{pic.shape[1]}×{pic.shape[0]} px · m = {use.render.samples} · "
                               f"ε = {use.render.eps:g} · "
                               f"{self.last_render_s * 1000:.0f} ms")
        return 1

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                sent = self.poll()
            except Exception as exc:  # noqa: BLE001 - keep serving whatever one render did
                log.warning("viewer: render failed: %s", exc)
                sent = 0
            if not sent:
                self._stop.wait(0.02)

    def close(self) -> None:
        """Stop the render thread and the web server."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
        self.server.stop()


def free_port(host: str = "127.0.0.1") -> int:
    """A currently free TCP port on ``host``."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def serve(model: ViewModel, cfg: ViewerConfig) -> None:
    """Serve ``model`` until interrupted (Ctrl-C)."""
    server = ViewerServer(model, cfg)
    log.info("viewer: %s (%s, %d points); Ctrl-C to stop", server.url, model.task, model.num_points)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
