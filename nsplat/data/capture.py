"""A user's own capture as the loaders return it: posed, undistorted views split into train and held-out.

The loaders (:mod:`nsplat.data.colmap`, :mod:`nsplat.data.transforms_json`) turn their files into
:class:`SourceView` s (photo, distorted camera, OpenCV world→camera pose); :func:`make_capture` reads the
photos at the requested downscale, undistorts them once into a cache (:mod:`nsplat.data.undistort`) and
splits them:

* **downscale** ``d > 1``: a photo ``<folder>/<rest>`` is read from ``<folder>_<d>/<rest>`` when that
  file exists (the ``images_2/4/8`` folders of Mip-NeRF 360, 3DGS and nerfstudio), else ``<folder>/<rest>``
  is resized by ``1/d`` here; the intrinsics are scaled by the actual size ratio.
* **cache**: undistorted photos go to ``<scene>/nsplat_undistorted/images_<d>/`` or, with ``cache_dir``,
  to ``<cache_dir>/<scene name>-<hash of its path>/images_<d>/``; photos of undistorted cameras are read
  as they are.
* **held-out views**: every ``holdout_every``-th view by sorted name, starting with the first (the
  ``llffhold = 8`` convention of the Mip-NeRF 360 and 3DGS evaluations).
* **views without a photo** (:func:`keep_present`): a frame or registered image whose photo is in neither folder is
  skipped with one warning naming how many and one of them (instant-ngp's demo folders and COLMAP models made
  before some photos were deleted list such frames), unless too few views remain for the split
  (:func:`fewest_views`): then a one-line :class:`DataError` says how many are needed.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
import math
from pathlib import Path, PurePosixPath
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch
import torch.nn.functional as F

from nsplat.data.undistort import UndistortCache, pinhole_camera, undistort_image
from nsplat.data.views import PosedViews
from nsplat.errors import DataError

#: Held-out views: every 8th by name (Mip-NeRF 360 / 3DGS).
HOLDOUT_EVERY = 8
#: Validation views: of the rest, every 8th from the 4th (``data.capture.val_every`` of the neural task).
VAL_EVERY = 8
CACHE_FOLDER = "nsplat_undistorted"

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class SourceView:
    """One posed photo as a loader found it, before downscaling and undistortion.

    Attributes:
        name: the view's name (sorting it gives the held-out split).
        rel: the photo's path relative to the scene folder; its first part is the image folder.
        camera: the distorted camera at the resolution the file describes.
        viewmat: ``[4,4]`` float64 OpenCV world→camera.
    """

    name: str
    rel: PurePosixPath
    camera: pycolmap.Camera
    viewmat: np.ndarray


@dataclasses.dataclass
class SfmPoints:
    """``P`` structure-from-motion points (a COLMAP ``points3D`` file).

    Attributes:
        xyz: ``[P,3]`` float32 world positions.
        rgb: ``[P,3]`` float32 colours in [0, 1].
        track_length: ``[P]`` int64 number of observing images.
        error: ``[P]`` float32 mean reprojection error in pixels (-1 where the model has none).
    """

    xyz: torch.Tensor
    rgb: torch.Tensor
    track_length: torch.Tensor
    error: torch.Tensor

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclasses.dataclass
class Capture:
    """A loaded capture.

    Attributes:
        train: training views (``masks`` and ``background`` ``None``: every pixel counts).
        test: the held-out views.
        cameras: view name → its distorted source camera as the file gives it (full resolution).
        points: the SfM points, where the source has them.
        metadata: what the source says about the scene beyond its views, kept as given (a ``transforms.json``'s
            ``aabb_scale``: :func:`nsplat.data.transforms_json.load_transforms`); nothing here is used to train.
    """

    train: PosedViews
    test: PosedViews
    cameras: dict[str, pycolmap.Camera]
    points: SfmPoints | None = None
    metadata: dict[str, object] = dataclasses.field(default_factory=dict)


def heldout_split(names: Sequence[str], every: int = HOLDOUT_EVERY) -> tuple[list[int], list[int]]:
    """``(train, test)`` indices into ``names``, each in sorted-name order: ``test`` holds every
    ``every``-th name of the sorted list starting with the first; ``every = 0`` holds none out."""
    if isinstance(every, bool) or not isinstance(every, int) or every < 0:
        raise ValueError(f"holdout_every: expected an integer >= 0, got {every!r}")
    order = sorted(range(len(names)), key=lambda i: names[i])
    test = set(order[::every]) if every else set()
    return [i for i in order if i not in test], [i for i in order if i in test]


def fewest_views(holdout_every: int = HOLDOUT_EVERY, val_every: int = VAL_EVERY) -> tuple[int, int, int, int]:
    """``(views, test, val, train)``: the fewest views whose split (:func:`heldout_split`, then every ``val_every``-th
    of the rest from the ``val_every // 2``-th for validation) leaves at least one training and one validation view
    (and with ``holdout_every`` one test view), and how many of each that is: ``(6, 1, 1, 4)`` for 8 and 8."""
    views = 1
    while True:
        test = len(range(0, views, holdout_every)) if holdout_every else 0
        val = len(range(val_every // 2, views - test, val_every))
        if val and views - test - val:
            return views, test, val, views - test - val
        views += 1


def photo_exists(scene: Path, rel: PurePosixPath, downscale: int) -> bool:
    """Whether the photo ``rel`` is in ``scene``, full size or as the ``<folder>_<downscale>`` copy :func:`_photo`
    reads."""
    if (scene / rel).is_file():
        return True
    head, *rest = rel.parts
    return downscale > 1 and bool(rest) and (scene / f"{head}_{downscale}" / PurePosixPath(*rest)).is_file()


def keep_present(scene: Path, rels: Sequence[PurePosixPath], *, downscale: int, holdout_every: int, where: Path,
                 what: str) -> list[int]:
    """The indices of ``rels`` (the photos of ``what``, e.g. "frames", listed in ``where``) whose photo exists.

    The others are skipped with one ``logging.warning`` line naming how many and one of them; when fewer remain
    than the split needs (:func:`fewest_views` of ``holdout_every``), a one-line :class:`DataError` says so.
    """
    keep = [i for i, rel in enumerate(rels) if photo_exists(scene, rel, downscale)]
    if len(keep) == len(rels):
        return keep
    kept = set(keep)
    example = next(rel for i, rel in enumerate(rels) if i not in kept)
    missing = f"{len(rels) - len(keep)} of the {len(rels)} {what} name a photo that is not in {scene} (e.g. {example})"
    views, test, val, train = fewest_views(holdout_every)
    if len(keep) < views:
        split = (f"one in {holdout_every} by name held out for testing, " if holdout_every else "") + (
            f"one in {VAL_EVERY} of the rest for validation")
        raise DataError(f"{where}: {missing}, which leaves {len(keep)}; at least {views} are needed ({split}: "
                        f"{test} test, {val} validation and {train} training views); add the missing photos")
    log.warning("%s: %s; training on the %d that have one", where, missing, len(keep))
    return keep


def cache_folder(scene: Path, cache_dir: str | Path | None, downscale: int) -> Path:
    """Where the undistorted photos of ``scene`` at ``downscale`` go."""
    if cache_dir is None:
        return scene / CACHE_FOLDER / f"images_{downscale}"
    digest = hashlib.sha1(str(scene.resolve()).encode()).hexdigest()[:8]
    return Path(cache_dir).expanduser() / f"{scene.resolve().name}-{digest}" / f"images_{downscale}"


def downscaled_size(width: int, height: int, downscale: int) -> tuple[int, int]:
    """``(W, H)`` of a photo shrunk by ``downscale`` (rounded half up, as ImageMagick's ``-resize``)."""
    return max(1, math.floor(width / downscale + 0.5)), max(1, math.floor(height / downscale + 0.5))


def _read(path: Path) -> np.ndarray:
    """``[H,W,3]`` uint8 or uint16 RGB (grey replicated, alpha dropped), or a one-line :class:`DataError`."""
    try:
        img = iio.imread(path)
    except Exception as exc:  # noqa: BLE001 - any decoder failure means an unreadable photo
        raise DataError(f"{path}: cannot read image (truncated or corrupt?): {exc}") from exc
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: expected an 8- or 16-bit grey, RGB or RGBA image, got shape {img.shape} {img.dtype}")
    return np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img[..., :3]


def _resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[H,W,C]`` → ``[H',W',C]`` for ``size = (W', H')``: area averaging for an integer factor, else
    antialiased bilinear."""
    H, W = x.shape[:2]
    if (W, H) == size:
        return x
    xc = x.permute(2, 0, 1)[None]
    if W % size[0] == 0 and H % size[1] == 0:
        out = F.interpolate(xc, size=(size[1], size[0]), mode="area")
    else:
        out = F.interpolate(xc, size=(size[1], size[0]), mode="bilinear", antialias=True, align_corners=False)
    return out[0].permute(1, 2, 0).contiguous()


def _photo(scene: Path, view: SourceView, downscale: int, where: Path) -> tuple[Path, np.ndarray, bool]:
    """``(path, pixels, from_folder)``: the photo at ``downscale``, from an ``<folder>_<d>`` copy when
    there is one (``from_folder``), else the full-size photo (not yet resized); sizes checked."""
    W, H = view.camera.width, view.camera.height
    parts = view.rel.parts
    if downscale > 1 and len(parts) > 1:
        small = scene / f"{parts[0]}_{downscale}" / PurePosixPath(*parts[1:])
        if small.is_file():
            img = _read(small)
            w, h = img.shape[1], img.shape[0]
            if abs(w * downscale - W) > downscale or abs(h * downscale - H) > downscale:
                raise DataError(f"{small}: image is {w}x{h}, expected {W}x{H} / {downscale} for camera "
                                f"{view.camera.camera_id} of {where}")
            return small, img, True
    path = scene / view.rel
    if not path.is_file():
        raise DataError(f"{where}: image {view.name!r} not found at {path}")
    img = _read(path)
    if (img.shape[1], img.shape[0]) != (W, H):
        turned = " (turned a quarter: photos are read as stored, without their EXIF orientation, as COLMAP, " \
                 "instant-ngp and nerfstudio read them)" if (img.shape[0], img.shape[1]) == (W, H) else ""
        raise DataError(f"{path}: image is {img.shape[1]}x{img.shape[0]} but camera {view.camera.camera_id} "
                        f"of {where} is {W}x{H}{turned}")
    return path, img, False


def _load_view(scene: Path, view: SourceView, downscale: int, cache: UndistortCache,
               where: Path) -> tuple[torch.Tensor, pycolmap.Camera]:
    """``(image [H,W,3] float32 in [0, 1], pinhole camera)`` of one view at ``downscale``."""
    path, img, from_folder = _photo(scene, view, downscale, where)
    scale = float(np.iinfo(img.dtype).max)
    size = (img.shape[1], img.shape[0]) if from_folder else downscaled_size(view.camera.width,
                                                                             view.camera.height, downscale)
    camera = copy.copy(view.camera)
    if size != (camera.width, camera.height):
        camera.rescale(*size)
    target = pinhole_camera(camera)
    if camera.is_undistorted():
        return _resize(torch.from_numpy(img.astype(np.float32) / scale), size), target
    key = cache.key(path, camera, target)
    cached = cache.get(view.name, key)
    if cached is None or cached.dtype != img.dtype:
        x = _resize(torch.from_numpy(img.astype(np.float32) / scale), size)
        out = undistort_image(x, camera, target)
        cached = np.round(out.clamp(0.0, 1.0).numpy() * scale).astype(img.dtype)
        cache.put(view.name, key, cached)
    return torch.from_numpy(cached.astype(np.float32) / scale), target


def _load_mask(scene: Path, masks: str, view: SourceView, size: tuple[int, int]) -> torch.Tensor:
    """``[H,W]`` float32 coverage in [0, 1] of one view at ``size = (W, H)``, from ``<masks>/<name>.png``
    (COLMAP's mask naming) or ``<masks>/<name>``, resized and undistorted like its photo."""
    folder = scene / masks
    path = next((p for p in (folder / f"{view.name}.png", folder / view.name) if p.is_file()), None)
    if path is None:
        raise DataError(f"{folder / (view.name + '.png')}: mask of image {view.name!r} not found")
    img = _read(path)
    if (img.shape[1], img.shape[0]) != (view.camera.width, view.camera.height):
        raise DataError(f"{path}: mask is {img.shape[1]}x{img.shape[0]}, its image's camera "
                        f"{view.camera.width}x{view.camera.height}")
    x = _resize(torch.from_numpy(img[..., :1].astype(np.float32) / float(np.iinfo(img.dtype).max)), size)
    camera = copy.copy(view.camera)
    if size != (camera.width, camera.height):
        camera.rescale(*size)
    if not camera.is_undistorted():
        x = undistort_image(x, camera, pinhole_camera(camera))
    return x[..., 0].clamp(0.0, 1.0)


def load_views(scene: Path, views: Sequence[SourceView], *, downscale: int, cache_dir: str | Path | None,
               where: Path, masks: str | None = None) -> PosedViews:
    """All ``views`` read at ``downscale``, undistorted (through the cache) and stacked, in the given order.

    Returns:
        :class:`PosedViews` with ``images [V,H,W,3]`` float32 in [0, 1], ``viewmats [V,4,4]``, pinhole
        ``Ks [V,3,3]`` (float32) and, with a ``masks`` folder (relative to ``scene``), ``masks [V,H,W]``
        float32 (else none); ``where`` (the model file) names the source in errors.
    """
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise ValueError(f"downscale: expected an integer >= 1, got {downscale!r}")
    if not views:
        raise DataError(f"{where}: no posed images")
    cache = UndistortCache(cache_folder(scene, cache_dir, downscale))
    images, Ks = [], []
    try:
        for view in views:
            img, target = _load_view(scene, view, downscale, cache, where)
            images.append(img)
            Ks.append(torch.from_numpy(target.calibration_matrix()))
    finally:
        cache.save()
    sizes = {tuple(img.shape[:2]): v.name for img, v in zip(images, views)}
    if len(sizes) > 1:
        (a, na), (b, nb) = list(sizes.items())[:2]
        raise DataError(f"{where}: views differ in size ({a[1]}x{a[0]} for {na!r}, {b[1]}x{b[0]} for {nb!r}); "
                        f"nsplat needs one image size per scene")
    viewmats = torch.from_numpy(np.stack([v.viewmat for v in views])).float()
    viewmats[:, 3] = torch.tensor([0.0, 0.0, 0.0, 1.0])
    size = (images[0].shape[1], images[0].shape[0])
    coverage = None if masks is None else torch.stack([_load_mask(scene, masks, v, size) for v in views])
    return PosedViews(images=torch.stack(images), viewmats=viewmats, Ks=torch.stack(Ks).float(),
                      names=[v.name for v in views], masks=coverage)


def make_capture(scene: Path, views: Sequence[SourceView], *, downscale: int, holdout_every: int,
                 cache_dir: str | Path | None, where: Path, points: SfmPoints | None = None,
                 masks: str | None = None, metadata: dict[str, object] | None = None) -> Capture:
    """Load ``views`` (:func:`load_views`, with ``masks``) and split them by :func:`heldout_split` into a
    :class:`Capture` (with ``metadata``)."""
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise DataError(f"{where}: image {dup!r} appears more than once")
    train, test = heldout_split(names, holdout_every)
    all_views = load_views(scene, [views[i] for i in train + test], downscale=downscale, cache_dir=cache_dir,
                           where=where, masks=masks)
    n = len(train)
    return Capture(train=all_views.subset(range(n)), test=all_views.subset(range(n, len(names))),
                   cameras={v.name: v.camera for v in views}, points=points, metadata=dict(metadata or {}))
