"""Loader for nerfstudio / instant-ngp captures: ``<scene>/transforms.json`` + the photos it names.

Intrinsics ``fl_x, fl_y, cx, cy, w, h`` and distortion ``k1, k2, p1, p2`` (``k3`` where present) are read
from the top level, and any frame may override any of them and ``camera_model`` (``OPENCV``, the default,
or ``PINHOLE``). An ``OPENCV`` camera becomes pycolmap's ``OPENCV`` camera, or ``FULL_OPENCV`` with
``k4 = k5 = k6 = 0`` when ``k3`` is non-zero (OpenCV's five-coefficient model); nerfstudio's ``k4`` (an
r⁸ term COLMAP has no model for) must be zero. ``cx, cy`` follow COLMAP (image from ``0`` to ``w``),
which is what nerfstudio's ``ns-process-data`` copies from COLMAP.

``transform_matrix`` is camera→world with OpenGL/Blender camera axes; it is converted once, here, to
OpenCV world→camera. ``applied_transform`` (3×4 or 4×4, written by ``ns-process-data``) is the rigid map
from the source reconstruction's world to this file's world (``x_file = A x_source``); with
``undo_applied_transform=True`` the cameras come back in the source world, where a COLMAP model's points
lie. Photos are downscaled, undistorted (cached) and split by :mod:`nsplat.data.capture`.
"""
from __future__ import annotations

import json
import math
from pathlib import Path, PurePosixPath

import numpy as np
import pycolmap
import torch

from nsplat.cameras import opengl_c2w_to_viewmat
from nsplat.data.capture import HOLDOUT_EVERY, Capture, SourceView, make_capture
from nsplat.errors import DataError

SUPPORTED_MODELS = ("OPENCV", "PINHOLE")
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
#: Allowed deviation of a rotation from orthonormal (``|RᵀR - I|``).
POSE_TOL = 1e-3


def _number(where: str, key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DataError(f"{where}: field {key!r}: expected a finite number, got {value!r}")
    return float(value)


def _matrix(where: str, value: object, rows: tuple[int, ...]) -> np.ndarray:
    """A rigid float64 4×4 transform from a ``rows``×4 nested list (last row ``[0, 0, 0, 1]`` if given)."""
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: expected a matrix of numbers") from None
    if m.ndim != 2 or m.shape[0] not in rows or m.shape[1] != 4:
        raise DataError(f"{where}: expected a {' or '.join(f'{r}x4' for r in rows)} matrix, got shape {list(m.shape)}")
    if not np.isfinite(m).all():
        raise DataError(f"{where}: contains NaN or Inf")
    if m.shape[0] == 4 and not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DataError(f"{where}: expected last row [0, 0, 0, 1], got {m[3].tolist()}")
    dev = float(np.abs(m[:3, :3].T @ m[:3, :3] - np.eye(3)).max())
    if dev > POSE_TOL or np.linalg.det(m[:3, :3]) < 0:
        raise DataError(f"{where}: the rotation part is not a rotation (|RᵀR - I| = {dev:.3g}, "
                        f"det {np.linalg.det(m[:3, :3]):.3g}); expected a rigid transform")
    out = np.eye(4)
    out[:3] = m[:3]
    return out


def _camera(meta_path: Path, i: int, meta: dict, frame: dict) -> pycolmap.Camera:
    """Frame ``i``'s camera (frame fields override the top level)."""
    where = f"{meta_path}: frame {i}"

    def field(key: str, default: float | None = None) -> float:
        value = frame.get(key, meta.get(key, default))
        if value is None:
            raise DataError(f"{where}: field {key!r} is missing (neither in the frame nor at the top level)")
        return _number(where, key, value)

    model = frame.get("camera_model", meta.get("camera_model", "OPENCV"))
    if model not in SUPPORTED_MODELS:
        raise DataError(f"{where}: camera_model {model!r} is not supported; supported: {', '.join(SUPPORTED_MODELS)}")
    fx, fy, cx, cy, w, h = (field(k) for k in INTRINSICS)
    if fx <= 0 or fy <= 0 or w < 1 or h < 1 or w != int(w) or h != int(h):
        raise DataError(f"{where}: expected positive fl_x, fl_y and whole positive w, h; got "
                        f"{fx:g}, {fy:g}, {w:g}, {h:g}")
    k1, k2, k3, k4, p1, p2 = (field(k, 0.0) for k in DISTORTION)
    if model == "PINHOLE":
        if any((k1, k2, k3, k4, p1, p2)):
            raise DataError(f"{where}: camera_model 'PINHOLE' with non-zero distortion; use 'OPENCV'")
        name, params = "PINHOLE", [fx, fy, cx, cy]
    elif k4:
        raise DataError(f"{where}: field 'k4' = {k4:g}: nerfstudio's r^8 term of the OPENCV model is not supported")
    elif k3:
        name, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    else:
        name, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return pycolmap.Camera(camera_id=i + 1, model=name, width=int(w), height=int(h), params=params)


def _file_path(meta_path: Path, i: int, value: object) -> PurePosixPath:
    if not isinstance(value, str) or not value:
        raise DataError(f"{meta_path}: frame {i}: field 'file_path': expected a non-empty string, got {value!r}")
    rel = PurePosixPath(value)
    return rel if rel.suffix else rel.with_suffix(".png")


def _read_meta(meta_path: Path) -> dict:
    """The parsed file, checked to be an object with a non-empty ``frames`` list."""
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{meta_path}: not valid JSON (truncated or corrupt?): {exc}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DataError(f"{meta_path}: expected an object with a non-empty list 'frames'")
    return meta


def point_cloud_path(scene: str | Path, file: str = "transforms.json") -> Path | None:
    """The point cloud the file names in ``ply_file_path`` (nerfstudio's ``ns-process-data`` writes the SfM
    points there, in the file's world), relative to ``scene``; ``None`` when it names none. A named file that
    does not exist is a :class:`DataError`."""
    meta_path = Path(scene) / file
    if not meta_path.is_file():
        raise FileNotFoundError(f"scene: no {file} in {scene}")
    value = _read_meta(meta_path).get("ply_file_path")
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise DataError(f"{meta_path}: field 'ply_file_path': expected a file name, got {value!r}")
    path = Path(scene) / value
    if not path.is_file():
        raise DataError(f"{meta_path}: field 'ply_file_path' names {path}, which does not exist")
    return path


def load_transforms(scene: str | Path, *, downscale: int = 1, holdout_every: int = HOLDOUT_EVERY,
                    undo_applied_transform: bool = False, file: str = "transforms.json",
                    cache_dir: str | Path | None = None, masks: str | None = None) -> Capture:
    """Load a nerfstudio / instant-ngp capture.

    Args:
        scene: folder holding ``file`` (paths in it are relative to this folder).
        downscale: read ``images_<downscale>/`` copies when they exist, else shrink the photos.
        holdout_every: every n-th frame by ``file_path`` is held out (8: Mip-NeRF 360 / 3DGS; 0: none).
        undo_applied_transform: return cameras in the source world of ``applied_transform``.
        file: the JSON file name.
        cache_dir: where undistorted photos go (default ``<scene>/nsplat_undistorted/``).
        masks: a folder (relative to ``scene``) of coverage masks, ``<file_path>.png`` or ``<file_path>`` per
            frame, resized and undistorted like the photos into ``views.masks``; ``None``: no masks.

    Returns:
        :class:`~nsplat.data.capture.Capture` (views named by ``file_path``; no SfM points: see
        :func:`point_cloud_path`).
    """
    scene = Path(scene)
    meta_path = scene / file
    if not meta_path.is_file():
        raise FileNotFoundError(f"scene: no {file} in {scene}")
    meta = _read_meta(meta_path)
    applied = np.eye(4)
    if "applied_transform" in meta:
        applied = _matrix(f"{meta_path}: field 'applied_transform'", meta["applied_transform"], (3, 4))
    source_from_file = np.linalg.inv(applied) if undo_applied_transform else np.eye(4)
    views = []
    for i, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict) or "transform_matrix" not in frame:
            raise DataError(f"{meta_path}: frame {i} lacks 'transform_matrix'")
        rel = _file_path(meta_path, i, frame.get("file_path"))
        c2w = _matrix(f"{meta_path}: frame {i}: field 'transform_matrix'", frame["transform_matrix"], (3, 4))
        viewmat = opengl_c2w_to_viewmat(torch.from_numpy(source_from_file @ c2w)).numpy()
        views.append(SourceView(name=str(rel), rel=rel, camera=_camera(meta_path, i, meta, frame), viewmat=viewmat))
    return make_capture(scene, views, downscale=downscale, holdout_every=holdout_every, cache_dir=cache_dir,
                        where=meta_path, masks=masks)
