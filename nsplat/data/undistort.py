"""Undistortion of real-capture photos to pinhole cameras, and the on-disk cache of the result.

All geometry comes from pycolmap's own camera models, so a loaded view agrees with the COLMAP model it
came from by construction:

* the target of a distorted camera is COLMAP's undistorted ``PINHOLE`` camera
  (``pycolmap.undistort_camera``: focal length kept, no blank pixels), rescaled to the source image's
  width × height so that every view of a scene keeps the size the user chose; a camera without
  distortion keeps its own ``fx, fy, cx, cy``;
* every target pixel centre samples the source photo (bilinear) where the source camera's
  ``img_from_cam`` projects the target pixel's ray.

Pixel coordinates follow COLMAP and the library: the image spans ``[0, W] × [0, H]``, pixel centres sit
at half-integers.

Why pycolmap and not kornia (measured, docs/capture.md): kornia's forward OpenCV distortion agrees with
``img_from_cam`` to 2e-8 px, but its fixed-iteration ``undistort_points`` is off ``cam_from_img`` by up to
1.2e-3 px in the corners of a 1600×1200 OPENCV camera with k1 = -0.12, where pycolmap's own round trip
is exact to 2e-8 px. On a rendered test pattern this warp is as close to the exact pinhole image as
``pycolmap.undistort_image`` and kornia's ``undistort_image`` (all within interpolation error, mean
0.5-0.7/255) and, unlike ``pycolmap.undistort_image``, works in floating point and keeps the source size.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch
import torch.nn.functional as F

from nsplat.errors import DataError

#: Bumped whenever the warp's output changes, so that stale cache entries are remade.
UNDISTORT_VERSION = 1
MANIFEST = "manifest.json"


def pinhole_camera(camera: pycolmap.Camera) -> pycolmap.Camera:
    """The ``PINHOLE`` camera of the same width × height that ``camera``'s photo is undistorted to."""
    if camera.is_undistorted():
        params = [camera.focal_length_x, camera.focal_length_y, camera.principal_point_x, camera.principal_point_y]
        return pycolmap.Camera(camera_id=camera.camera_id, model="PINHOLE", width=camera.width,
                               height=camera.height, params=params)
    target = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
    target.rescale(camera.width, camera.height)
    return target


def pixel_centres(width: int, height: int) -> np.ndarray:
    """``[H*W, 2]`` float64 pixel-centre coordinates ``(u, v)`` in row-major order."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([u.ravel(), v.ravel()], 1)


def _homogeneous(xy: np.ndarray) -> np.ndarray:
    """``[N,2]`` normalised image coordinates → ``[N,3]`` rays with ``z = 1``."""
    return np.concatenate([xy, np.ones((len(xy), 1))], 1)


def undistort_points(uv: np.ndarray, source: pycolmap.Camera, target: pycolmap.Camera) -> np.ndarray:
    """Pixel positions ``uv [N,2]`` of the distorted ``source`` camera → ``[N,2]`` in ``target``."""
    return target.img_from_cam(_homogeneous(source.cam_from_img(np.asarray(uv, dtype=np.float64))))


def source_positions(source: pycolmap.Camera, target: pycolmap.Camera) -> np.ndarray:
    """``[H_t, W_t, 2]``: for every ``target`` pixel centre, where its ray lands in the ``source`` photo."""
    rays = target.cam_from_img(pixel_centres(target.width, target.height))
    return source.img_from_cam(_homogeneous(rays)).reshape(target.height, target.width, 2)


def undistort_image(image: torch.Tensor, source: pycolmap.Camera, target: pycolmap.Camera) -> torch.Tensor:
    """Warp ``image [H,W,C]`` (float, of ``source``'s size) to ``target``: ``[H_t, W_t, C]``, bilinear.

    Positions a fraction of a pixel outside the source (COLMAP's no-blank-pixel camera allows it at the
    border) take the nearest border pixel.
    """
    pos = torch.from_numpy(source_positions(source, target))
    grid = pos * torch.tensor([2.0 / source.width, 2.0 / source.height], dtype=torch.float64) - 1.0
    out = F.grid_sample(image.permute(2, 0, 1)[None], grid[None].to(image.dtype), mode="bilinear",
                        padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0).contiguous()


def _camera_key(camera: pycolmap.Camera) -> list[object]:
    return [camera.model_name, int(camera.width), int(camera.height), [float(p) for p in camera.params]]


class UndistortCache:
    """A folder of undistorted photos (PNG, the source's bit depth) with a ``manifest.json``.

    The manifest maps each view name to the key its file was made from: the source file, its size and
    modification time, the source and target cameras and :data:`UNDISTORT_VERSION`. A view whose key
    differs (the photo or the model changed) is remade; :meth:`save` writes the manifest.
    """

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        path = folder / MANIFEST
        try:
            self.entries: dict[str, object] = json.loads(path.read_text()) if path.is_file() else {}
        except (json.JSONDecodeError, UnicodeDecodeError):
            self.entries = {}  # a damaged manifest only costs a rebuild
        self._dirty = False

    @staticmethod
    def key(path: Path, source: pycolmap.Camera, target: pycolmap.Camera) -> dict[str, object]:
        """The cache key of the photo at ``path`` warped from ``source`` to ``target``."""
        st = path.stat()
        return {"version": UNDISTORT_VERSION, "source": str(path.resolve()), "bytes": st.st_size,
                "mtime_ns": st.st_mtime_ns, "camera": _camera_key(source), "target": _camera_key(target)}

    def _file(self, name: str) -> Path:
        return self.folder / (name if name.lower().endswith(".png") else f"{name}.png")

    def get(self, name: str, key: dict[str, object]) -> np.ndarray | None:
        """The cached ``[H,W,3]`` integer image of view ``name`` when its key matches, else ``None``."""
        file = self._file(name)
        if self.entries.get(name) != key or not file.is_file():
            return None
        try:
            return iio.imread(file)
        except Exception:  # noqa: BLE001 - an unreadable cache file is remade
            return None

    def put(self, name: str, key: dict[str, object], image: np.ndarray) -> None:
        """Store view ``name``'s undistorted ``[H,W,3]`` integer image under ``key``."""
        file = self._file(name)
        try:
            file.parent.mkdir(parents=True, exist_ok=True)
            iio.imwrite(file, image)
        except OSError as exc:
            raise DataError(f"{self.folder}: cannot write the undistortion cache ({exc}); "
                            f"pass cache_dir= to put it elsewhere") from exc
        self.entries[name] = key
        self._dirty = True

    def save(self) -> None:
        """Write the manifest (atomically) when an entry changed."""
        if not self._dirty:
            return
        tmp = self.folder / f".{MANIFEST}.{os.getpid()}.tmp"
        tmp.write_text(json.dumps(self.entries, indent=1, sort_keys=True))
        os.replace(tmp, self.folder / MANIFEST)
        self._dirty = False
