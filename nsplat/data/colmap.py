"""Loader for COLMAP sparse models: ``<scene>/sparse/<k>/{cameras,images,points3D}.{bin,txt}`` + ``<scene>/images/``
(of several models ``sparse/0``, ``sparse/1``, ..., the one with the most registered images).

The model is read with pycolmap (after :mod:`nsplat.data.colmap_check` has checked that its files are
whole); camera models ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL`` and ``OPENCV`` are
accepted. COLMAP's poses are already OpenCV world→camera (``cam_from_world``), so they are used as they
are. Registered images whose photo is missing are skipped with one warning unless too few remain
(:func:`nsplat.data.capture.keep_present`). Photos are downscaled, undistorted (cached) and split by
:mod:`nsplat.data.capture`; the SfM points come back too, for initialisation. Layouts and conventions:
docs/capture.md.
"""
from __future__ import annotations

import copy
import logging
import re
from pathlib import Path, PurePosixPath

import numpy as np
import pycolmap
import torch

from nsplat.data.capture import HOLDOUT_EVERY, Capture, SfmPoints, SourceView, keep_present, make_capture
from nsplat.data.colmap_check import check_binary, check_text
from nsplat.errors import DataError

SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
REQUIRED = ("cameras", "images", "points3D")
#: Written by COLMAP >= 3.12 (camera rigs); older models lack both.
RIG_FILES = ("rigs", "frames")

log = logging.getLogger(__name__)


def _has_model(folder: Path) -> bool:
    return any((folder / f"cameras{ext}").is_file() for ext in (".bin", ".txt"))


def registered_images(folder: Path) -> int:
    """Number of registered images of the model in ``folder``, from the head of ``images.bin`` (its record
    count) or ``images.txt`` (its ``# Number of images`` header, else two lines per image); 0 when absent."""
    binary, text = folder / "images.bin", folder / "images.txt"
    if binary.is_file():
        with open(binary, "rb") as fh:
            head = fh.read(8)
        return int.from_bytes(head, "little") if len(head) == 8 else 0
    if text.is_file():
        lines = text.read_text(errors="replace").splitlines()
        for line in lines:
            match = _IMAGES_HEADER.match(line)
            if match:
                return int(match.group(1))
        return (len([ln for ln in lines if not ln.startswith("#")]) + 1) // 2
    return 0


_IMAGES_HEADER = re.compile(r"#\s*Number of images:\s*(\d+)")


def find_model(scene: Path, sparse: str | None = None) -> Path:
    """The sparse model folder of ``scene``: ``sparse`` (relative to it) when given; else, of the models in
    ``sparse/<k>/`` (COLMAP's mapper writes one per connected group of images), the one with the most
    registered images (the lowest ``k`` on a tie), logging the choice when there are several; else ``sparse``
    when that holds the files itself."""
    if sparse is not None:
        return scene / sparse
    root = scene / "sparse"
    models = sorted((d for d in root.iterdir() if d.is_dir() and d.name.isdigit() and _has_model(d)),
                    key=lambda d: int(d.name)) if root.is_dir() else []
    if len(models) > 1:
        counts = {d: registered_images(d) for d in models}
        best = max(models, key=lambda d: counts[d])  # max keeps the first of equal counts
        listed = ", ".join(f"{d.relative_to(scene)} ({counts[d]} images)" for d in models)
        log.info("COLMAP: %s holds %d models: %s; loading %s, the one with the most registered images "
                 "(data.capture.sparse, or sparse= of load_colmap, picks another)", root, len(models), listed,
                 best.relative_to(scene))
        return best
    if models:
        return models[0]
    return root if _has_model(root) else root / "0"


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def read_model(folder: Path) -> tuple[pycolmap.Reconstruction, str]:
    """Read the COLMAP model in ``folder`` (binary preferred, as COLMAP does) with pycolmap.

    Returns:
        ``(reconstruction, ext)`` with ``ext`` ``".bin"`` or ``".txt"``. Missing, truncated or unreadable
        files and unsupported camera models raise a one-line :class:`DataError` naming the file.
    """
    ext = next((e for e in (".bin", ".txt") if (folder / f"cameras{e}").is_file()), None)
    if ext is None:
        raise DataError(f"{folder / 'cameras.bin'}: not found (nor cameras.txt): expected a COLMAP sparse model "
                        f"with {', '.join(REQUIRED)} .bin or .txt files")
    for kind in REQUIRED:
        if not (folder / f"{kind}{ext}").is_file():
            raise DataError(f"{folder / (kind + ext)}: not found; a COLMAP sparse model needs "
                            f"{', '.join(k + ext for k in REQUIRED)}")
    present = [k for k in RIG_FILES if (folder / f"{k}{ext}").is_file()]
    if len(present) == 1:
        missing = next(k for k in RIG_FILES if k not in present)
        raise DataError(f"{folder / (missing + ext)}: not found, but {present[0]}{ext} is: the model is partial")
    check = check_binary if ext == ".bin" else check_text
    for kind in (*REQUIRED, *present):
        check(folder / f"{kind}{ext}")
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_binary if ext == ".bin" else rec.read_text)(str(folder))
    except (ValueError, IndexError, RuntimeError, MemoryError) as exc:
        raise DataError(f"{folder}: pycolmap cannot read the {ext} model (corrupt or inconsistent files): "
                        f"{_one_line(exc)}") from exc
    for camera_id, camera in sorted(rec.cameras.items()):
        if camera.model_name not in SUPPORTED_MODELS:
            raise DataError(f"{folder / ('cameras' + ext)}: camera {camera_id} uses model {camera.model_name}; "
                            f"supported: {', '.join(SUPPORTED_MODELS)}")
    return rec, ext


def sfm_points(rec: pycolmap.Reconstruction) -> SfmPoints:
    """The model's 3D points in increasing id order."""
    ids = sorted(rec.point3D_ids())
    pts = [rec.points3D[i] for i in ids]
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    return SfmPoints(xyz=torch.from_numpy(xyz).float(), rgb=torch.from_numpy(rgb.astype(np.float32) / 255.0),
                     track_length=torch.tensor([p.track.length() for p in pts], dtype=torch.int64),
                     error=torch.tensor([p.error for p in pts], dtype=torch.float32))


def _viewmat(image: pycolmap.Image) -> np.ndarray:
    """``[4,4]`` float64 OpenCV world→camera of a registered image."""
    V = np.eye(4)
    V[:3] = image.cam_from_world().matrix()
    return V


def load_colmap(scene: str | Path, *, downscale: int = 1, holdout_every: int = HOLDOUT_EVERY,
                images: str = "images", sparse: str | None = None,
                cache_dir: str | Path | None = None, masks: str | None = None) -> Capture:
    """Load a COLMAP capture: the registered images of the sparse model with their photos.

    Args:
        scene: folder holding ``sparse/<k>/`` (or ``sparse/``) and the photo folder.
        downscale: read ``<images>_<downscale>/`` when it exists, else shrink ``<images>/`` by this factor.
        holdout_every: every n-th image by name is held out (8: Mip-NeRF 360 / 3DGS; 0: none).
        images: the photo folder, relative to ``scene`` (image names in the model are relative to it).
        sparse: the model folder relative to ``scene`` (default: :func:`find_model`: the model with the most
            registered images).
        cache_dir: where undistorted photos go (default ``<scene>/nsplat_undistorted/``).
        masks: a folder (relative to ``scene``) of coverage masks, ``<name>.png`` or ``<name>`` per image
            (COLMAP's naming), resized and undistorted like the photos into ``views.masks`` (e.g. for a
            visual hull); ``None``: no masks.

    Returns:
        :class:`~nsplat.data.capture.Capture`: train/test :class:`~nsplat.data.views.PosedViews`
        (float32 images ``[V,H,W,3]``, OpenCV world→camera ``viewmats``, pinhole ``Ks``, masks as above), the
        source cameras by image name, and the SfM points.
    """
    scene = Path(scene)
    if not scene.is_dir():
        raise FileNotFoundError(f"scene: not a folder: {scene}")
    folder = find_model(scene, sparse)
    rec, ext = read_model(folder)
    where = folder / f"images{ext}"
    registered = [rec.images[image_id] for image_id in sorted(rec.reg_image_ids())]
    rels = [PurePosixPath(images) / image.name for image in registered]
    views = []
    for i in keep_present(scene, rels, downscale=downscale, holdout_every=holdout_every, where=where,
                          what="registered images"):
        image = registered[i]
        V = _viewmat(image)
        if not np.isfinite(V).all():
            raise DataError(f"{where}: image {image.name!r}: pose contains NaN or Inf")
        views.append(SourceView(name=image.name, rel=rels[i], camera=copy.copy(rec.cameras[image.camera_id]),
                                viewmat=V))
    return make_capture(scene, views, downscale=downscale, holdout_every=holdout_every, cache_dir=cache_dir,
                        where=where, points=sfm_points(rec), masks=masks)
