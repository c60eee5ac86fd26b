"""Loader for nerfstudio / instant-ngp captures: ``<scene>/transforms.json`` + the photos it names.

The fields are read as instant-ngp and nerfstudio read them (docs/capture.md, "nerfstudio / instant-ngp"):

* intrinsics ``fl_x, fl_y, cx, cy, w, h``, distortion ``k1 k2 k3 k4 p1 p2`` and ``camera_model`` at the top level,
  and any frame may give its own, which override them (per-frame intrinsics: several cameras in one file).
  Without ``fl_x``/``fl_y``, the field of view ``camera_angle_x``/``camera_angle_y`` (radians; instant-ngp's and
  NeRF's) or ``x_fov``/``y_fov`` (degrees) gives it; one axis alone gives both (square pixels). ``cx, cy`` default
  to the image centre and ``w, h`` to the photo's size as stored (no EXIF rotation: a portrait photo is one stored
  portrait, ``w < h``).
* ``camera_model`` (COLMAP's names, as nerfstudio writes them): ``OPENCV`` (the default; also ``SIMPLE_PINHOLE``,
  ``SIMPLE_RADIAL`` and ``RADIAL``, read with the same fields) becomes pycolmap's ``OPENCV`` camera, or
  ``FULL_OPENCV`` with ``k4 = k5 = k6 = 0`` when ``k3`` is non-zero (OpenCV's five-coefficient model);
  nerfstudio's ``k4`` (an r⁸ term COLMAP has no model for) must be zero. ``OPENCV_FISHEYE`` (or instant-ngp's
  ``is_fisheye: true``) is pycolmap's ``OPENCV_FISHEYE`` with ``k1 k2 k3 k4``; ``PINHOLE`` has no distortion.
  ``cx, cy`` follow COLMAP (image from ``0`` to ``w``), which is what ``ns-process-data`` and instant-ngp's
  ``colmap2nerf.py`` copy from COLMAP.
* frames whose photo is missing are skipped with one warning, unless too few remain
  (:func:`nsplat.data.capture.keep_present`); a ``file_path`` without extension is tried as instant-ngp does.
* ``aabb_scale`` (instant-ngp: how many times the unit cube its own normalisation fits the cameras in the scene
  extends, a power of two up to 128 that bounds the region its rays march through, for far backgrounds) is kept
  in :attr:`Capture.metadata <nsplat.data.capture.Capture.metadata>`; nothing here uses it.

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

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch

from nsplat.cameras import opengl_c2w_to_viewmat
from nsplat.data.capture import HOLDOUT_EVERY, Capture, SourceView, keep_present, make_capture
from nsplat.errors import DataError

#: ``camera_model`` values (COLMAP's names, as nerfstudio writes them): ``PINHOLE`` (no distortion),
#: ``OPENCV_FISHEYE`` (``k1 k2 k3 k4``) and the perspective models nerfstudio reads with ``k1 k2 (k3) p1 p2``.
SUPPORTED_MODELS = ("OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
#: The focal-length fields of each axis in instant-ngp's order of precedence: degrees, pixels, radians.
FOCAL = {"x": ("x_fov", "fl_x", "camera_angle_x"), "y": ("y_fov", "fl_y", "camera_angle_y")}
#: Extensions tried, in instant-ngp's order, for a ``file_path`` without one (``.png`` when none exists).
EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tga")
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


def _image_size(path: Path, where: str) -> tuple[int, int]:
    """``(w, h)`` of the photo at ``path`` as stored, for a frame that gives no ``w`` or ``h``."""
    if not path.is_file():
        raise DataError(f"{where}: fields 'w' and 'h' are not given and there is no full-size photo {path} to take "
                        f"them from")
    try:
        shape = iio.improps(path).shape
    except Exception as exc:  # noqa: BLE001 - any decoder failure means an unreadable photo
        raise DataError(f"{path}: cannot read image (truncated or corrupt?): {exc}") from exc
    return int(shape[1]), int(shape[0])


def _focal(where: str, frame: dict, meta: dict, axis: str, size: float) -> float | None:
    """The focal length in pixels along ``axis`` (``x`` or ``y``, the image ``size`` pixels long) from the first of
    :data:`FOCAL` in the frame, else at the top level (as instant-ngp reads them); ``None`` when neither has one."""
    for fields in (frame, meta):
        key = next((k for k in FOCAL[axis] if k in fields), None)
        if key is None:
            continue
        value = _number(where, key, fields[key])
        if key.startswith("fl_"):
            return value
        angle, top = (math.radians(value), "180 degrees") if key.endswith("_fov") else (value, "pi radians")
        if not 0.0 < angle < math.pi:
            raise DataError(f"{where}: field {key!r}: expected a field of view between 0 and {top}, got {value:g}")
        return 0.5 * size / math.tan(0.5 * angle)
    return None


def _camera(meta_path: Path, i: int, meta: dict, frame: dict, photo: Path) -> pycolmap.Camera:
    """Frame ``i``'s camera: frame fields override the top level; ``w``, ``h`` default to the size of the full-size
    ``photo`` as stored, ``cx``, ``cy`` to the image centre, ``fl_y`` to ``fl_x`` and back (instant-ngp's rules)."""
    where = f"{meta_path}: frame {i}"

    def field(key: str) -> float | None:
        value = frame.get(key, meta.get(key))
        return None if value is None else _number(where, key, value)

    fisheye = frame.get("is_fisheye", meta.get("is_fisheye")) is True  # instant-ngp's flag
    model = frame.get("camera_model", meta.get("camera_model", "OPENCV_FISHEYE" if fisheye else "OPENCV"))
    if model not in SUPPORTED_MODELS:
        raise DataError(f"{where}: camera_model {model!r} is not supported; supported: {', '.join(SUPPORTED_MODELS)}")
    w, h = field("w"), field("h")
    if w is None or h is None:
        size = _image_size(photo, where)
        w, h = size[0] if w is None else w, size[1] if h is None else h
    fx, fy = _focal(where, frame, meta, "x", w), _focal(where, frame, meta, "y", h)
    if fx is None and fy is None:
        raise DataError(f"{where}: no focal length: none of {', '.join(FOCAL['x'] + FOCAL['y'])} in the frame or at "
                        f"the top level")
    fx, fy = fy if fx is None else fx, fx if fy is None else fy
    cx, cy = field("cx"), field("cy")
    cx, cy = w / 2 if cx is None else cx, h / 2 if cy is None else cy
    if fx <= 0 or fy <= 0 or w < 1 or h < 1 or w != int(w) or h != int(h):
        raise DataError(f"{where}: expected positive fl_x, fl_y and whole positive w, h; got "
                        f"{fx:g}, {fy:g}, {w:g}, {h:g}")
    k1, k2, k3, k4, p1, p2 = (field(k) or 0.0 for k in DISTORTION)
    if model == "PINHOLE":
        if any((k1, k2, k3, k4, p1, p2)):
            raise DataError(f"{where}: camera_model 'PINHOLE' with non-zero distortion; use 'OPENCV'")
        name, params = "PINHOLE", [fx, fy, cx, cy]
    elif model == "OPENCV_FISHEYE":
        if p1 or p2:
            raise DataError(f"{where}: camera_model 'OPENCV_FISHEYE' with non-zero p1 or p2: the fisheye model has "
                            f"k1..k4 only")
        name, params = "OPENCV_FISHEYE", [fx, fy, cx, cy, k1, k2, k3, k4]
    elif k4:
        raise DataError(f"{where}: field 'k4' = {k4:g}: nerfstudio's r^8 term of the OPENCV model is not supported")
    elif k3:
        name, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    else:
        name, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return pycolmap.Camera(camera_id=i + 1, model=name, width=int(w), height=int(h), params=params)


def _file_path(scene: Path, meta_path: Path, i: int, value: object) -> PurePosixPath:
    """Frame ``i``'s photo relative to ``scene`` (Windows separators allowed; without an extension, the first of
    :data:`EXTENSIONS` that exists, else ``.png``)."""
    if not isinstance(value, str) or not value:
        raise DataError(f"{meta_path}: frame {i}: field 'file_path': expected a non-empty string, got {value!r}")
    rel = PurePosixPath(value.replace("\\", "/"))
    if rel.suffix:
        return rel
    return next((rel.with_suffix(e) for e in EXTENSIONS if (scene / rel.with_suffix(e)).is_file()),
                rel.with_suffix(".png"))


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
    metadata: dict[str, object] = {}
    if "aabb_scale" in meta:
        metadata["aabb_scale"] = _number(str(meta_path), "aabb_scale", meta["aabb_scale"])
        if metadata["aabb_scale"] <= 0:
            raise DataError(f"{meta_path}: field 'aabb_scale': expected a positive number, got {meta['aabb_scale']!r}")
    source_from_file = np.linalg.inv(applied) if undo_applied_transform else np.eye(4)
    frames, rels = meta["frames"], []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or "transform_matrix" not in frame:
            raise DataError(f"{meta_path}: frame {i} lacks 'transform_matrix'")
        rels.append(_file_path(scene, meta_path, i, frame.get("file_path")))
    views = []
    for i in keep_present(scene, rels, downscale=downscale, holdout_every=holdout_every, where=meta_path,
                          what="frames"):
        c2w = _matrix(f"{meta_path}: frame {i}: field 'transform_matrix'", frames[i]["transform_matrix"], (3, 4))
        viewmat = opengl_c2w_to_viewmat(torch.from_numpy(source_from_file @ c2w)).numpy()
        camera = _camera(meta_path, i, meta, frames[i], scene / rels[i])
        views.append(SourceView(name=str(rels[i]), rel=rels[i], camera=camera, viewmat=viewmat))
    return make_capture(scene, views, downscale=downscale, holdout_every=holdout_every, cache_dir=cache_dir,
                        where=meta_path, masks=masks, metadata=metadata)
