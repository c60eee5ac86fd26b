"""Points for a posed capture that ships none: triangulated from its photos with the poses held, or the SfM points of
a COLMAP model beside it.

instant-ngp's ``colmap2nerf.py`` writes a ``transforms.json`` without points, so a folder made by it gives the poses
and intrinsics but nothing to start the surfels from. Two sources, tried in this order by
:func:`nsplat.tasks.neural.capture.prepare`:

* **a COLMAP model beside it** (:func:`colmap_points_beside`: ``sparse/0``, ``colmap/sparse/0`` or ``sparse``, the
  folders colmap2nerf and ``ns-process-data`` leave): its points, moved into the file's world by the similarity
  that maps the model's camera centres onto the file's (fitted on the images both name; colmap2nerf re-orients,
  re-centres and scales the world without recording how). A model whose cameras do not fit the file's within
  :data:`FIT_TOLERANCE` is passed over with a warning.
* **triangulation** (:func:`triangulate`): SIFT features of the training photos as loaded (undistorted, at the
  training resolution), matched exhaustively (sequentially by name beyond :data:`EXHAUSTIVE_MAX` views),
  then pycolmap's ``triangulate_points`` with every camera held at the file's pose and intrinsics. About a
  second for a dozen 128-pixel photos and some tens of seconds for fifty 240-pixel ones on 2 CPU cores;
  the result is cached (:func:`cached_triangulation`) under a key of the photos, poses and intrinsics.

Both return :class:`~nsplat.data.capture.SfmPoints` in the capture's world, as a COLMAP capture's loader does.
"""
from __future__ import annotations

import hashlib
import logging
import shutil
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch

from nsplat.cameras import camera_centres
from nsplat.data.capture import SfmPoints
from nsplat.data.colmap import read_model, sfm_points
from nsplat.data.views import PosedViews
from nsplat.errors import DataError

log = logging.getLogger(__name__)

#: Bumped whenever the triangulation's output changes, so stale caches are not reused.
TRIANGULATION_VERSION = 1
#: Views up to which every pair is matched; beyond, each view is matched with its neighbours by name.
EXHAUSTIVE_MAX = 150
#: Neighbours by name a view is matched with beyond :data:`EXHAUSTIVE_MAX` views.
SEQUENTIAL_OVERLAP = 20
#: SIFT's peak threshold: COLMAP's 0.0067 finds too few blobs in photos a few hundred pixels wide.
PEAK_THRESHOLD = 0.004
#: COLMAP's own log lines shown during the triangulation (glog's levels: 2, errors only; its progress lines are
#: summed up in one line of this module's log).
COLMAP_LOG_LEVEL = 2
#: COLMAP model folders looked for beside a ``transforms.json``, in this order.
BESIDE = ("sparse/0", "colmap/sparse/0", "sparse")
#: Largest median residual of a model's fitted camera centres (in units of the cameras' spread about their mean)
#: or camera rotations (degrees) for its points to be used.
FIT_TOLERANCE = (0.01, 2.0)


def _digest(views: PosedViews) -> str:
    """Key of ``views``: names, size, poses, intrinsics and photos (8-bit), and :data:`TRIANGULATION_VERSION`."""
    h = hashlib.sha256(f"{TRIANGULATION_VERSION} {views.width}x{views.height} {views.names}".encode())
    for t in (views.viewmats, views.Ks, _bytes(views.images)):
        h.update(np.ascontiguousarray(t.cpu().numpy()).tobytes())
    return h.hexdigest()[:16]


def _bytes(images: torch.Tensor) -> torch.Tensor:
    """``images [B,H,W,3]`` float in [0, 1] as uint8 (what the feature extractor reads)."""
    return (images[..., :3].cpu() * 255.0 + 0.5).clamp(0, 255).to(torch.uint8)


def _pinhole(K: np.ndarray, camera_id: int, width: int, height: int) -> pycolmap.Camera:
    return pycolmap.Camera(camera_id=camera_id, model="PINHOLE", width=width, height=height,
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def triangulate(views: PosedViews, work: Path, threads: int = 1) -> SfmPoints:
    """Points triangulated from the photos of ``views`` with their poses and intrinsics held fixed.

    Args:
        views: posed, undistorted views (``images [V,H,W,3]`` in [0, 1], OpenCV world→camera
            ``viewmats [V,4,4]``, pinhole ``Ks [V,3,3]``), at least two.
        work: an empty folder for the photos (PNG) and pycolmap's database.
        threads: CPU threads of the extraction, matching and triangulation.

    Returns:
        :class:`SfmPoints` ``[P]`` in the views' world (track lengths and reprojection errors from pycolmap, colours
        from the photos); ``P`` may be 0 for photos without texture.
    """
    if len(views) < 2:
        raise ValueError(f"triangulation needs at least 2 posed views, got {len(views)}")
    quiet = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = COLMAP_LOG_LEVEL
    try:
        return _triangulate(views, work, threads)
    finally:
        pycolmap.logging.minloglevel = quiet


def _triangulate(views: PosedViews, work: Path, threads: int) -> SfmPoints:
    """:func:`triangulate`, with COLMAP's own log lines held back."""
    t0 = time.perf_counter()
    folder, db = work / "images", work / "database.db"
    folder.mkdir(parents=True)
    names = [f"{i:05d}.png" for i in range(len(views))]
    pixels = _bytes(views.images).numpy()
    for name, img in zip(names, pixels):
        iio.imwrite(folder / name, img)
    extraction = pycolmap.FeatureExtractionOptions(num_threads=threads)
    extraction.sift.peak_threshold = PEAK_THRESHOLD
    pycolmap.extract_features(db, folder, image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=pycolmap.ImageReaderOptions(camera_model="PINHOLE"),
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    t1 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions(num_threads=threads)
    if len(views) <= EXHAUSTIVE_MAX:
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions(overlap=SEQUENTIAL_OVERLAP, quadratic_overlap=False)
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    t2 = time.perf_counter()
    rec = pycolmap.Reconstruction()
    database = pycolmap.Database.open(db)
    try:
        Ks, viewmats = views.Ks.double().cpu().numpy(), views.viewmats.double().cpu().numpy()
        for image in database.read_all_images():
            i = names.index(image.name)
            camera = _pinhole(Ks[i], image.camera_id, views.width, views.height)
            database.update_camera(camera)       # the file's intrinsics, not the extractor's guess
            rec.add_camera_with_trivial_rig(camera)
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(viewmats[i, :3, :3]), viewmats[i, :3, 3])
            rec.add_image_with_trivial_frame(pycolmap.Image(image_id=image.image_id, name=image.name,
                                                            camera_id=image.camera_id), pose)
    finally:
        database.close()
    (work / "model").mkdir()
    options = pycolmap.IncrementalPipelineOptions(num_threads=threads, random_seed=0)
    out = pycolmap.triangulate_points(rec, db, folder, work / "model", options=options)
    points = sfm_points(out)
    log.info("triangulated %d points from %d posed views (%dx%d) in %.1f s: features %.1f s, matching %.1f s, "
             "triangulation %.1f s; mean track %.1f views, mean reprojection error %.2f px", len(points), len(views),
             views.width, views.height, time.perf_counter() - t0, t1 - t0, t2 - t1, time.perf_counter() - t2,
             float(points.track_length.double().mean()) if len(points) else 0.0,
             float(points.error.double().mean()) if len(points) else 0.0)
    return points


def cached_triangulation(views: PosedViews, cache: Path, threads: int = 1) -> SfmPoints:
    """:func:`triangulate` of ``views``, read from ``cache/<key>.npz`` when it holds them (the key digests the
    photos, poses and intrinsics: any change triangulates anew), else computed and written there."""
    path = Path(cache) / f"{_digest(views)}.npz"
    if path.is_file():
        with np.load(path) as z:
            points = SfmPoints(xyz=torch.from_numpy(z["xyz"]), rgb=torch.from_numpy(z["rgb"]),
                               track_length=torch.from_numpy(z["track_length"]), error=torch.from_numpy(z["error"]))
        log.info("triangulated points: %d from the cache %s", len(points), path)
        return points
    log.info("triangulating points from the %d training views with their poses held (pycolmap: SIFT features, "
             "%s matching; cached in %s) ...", len(views), "exhaustive" if len(views) <= EXHAUSTIVE_MAX else
             "sequential", path.parent)
    work = Path(tempfile.mkdtemp(prefix="nsplat-triangulate-"))
    try:
        points = triangulate(views, work, threads)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, xyz=points.xyz.numpy(), rgb=points.rgb.numpy(), track_length=points.track_length.numpy(),
             error=points.error.numpy())
    tmp.replace(path)
    return points


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R [3,3], t [3])`` minimising ``Σ |s R src_i + t − dst_i|²`` over points ``src, dst [N,3]`` float64
    (Umeyama's least-squares similarity; ``R`` a proper rotation)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, md - s * R @ ms


def _name_key(name: str) -> str:
    """A view's photo name without its folder (COLMAP names images relative to the photo folder, a
    ``transforms.json`` relative to the scene)."""
    return name.replace("\\", "/").rsplit("/", 1)[-1]


def colmap_points_beside(scene: Path, views: PosedViews) -> tuple[SfmPoints, Path] | None:
    """The SfM points of the first COLMAP model of :data:`BESIDE` in ``scene`` that registers at least 3 of the
    photos of ``views`` (matched by file name), moved into the world of ``views`` by the similarity fitted to
    their camera centres; ``None`` when there is no such model or its cameras do not fit (a warning)."""
    for sub in BESIDE:
        folder = scene / sub
        if not (folder / "cameras.bin").is_file() and not (folder / "cameras.txt").is_file():
            continue
        try:
            rec, _ = read_model(folder)
        except DataError as exc:
            log.warning("%s: not used for the start: %s", folder, exc)
            continue
        by_name = {_name_key(rec.images[i].name): rec.images[i] for i in rec.reg_image_ids()}
        pairs = [(i, by_name[_name_key(n)]) for i, n in enumerate(views.names) if _name_key(n) in by_name]
        if len(pairs) < 3 or rec.num_points3D() == 0:
            continue
        model = np.stack([im.projection_center() for _, im in pairs])
        mine = camera_centres(views.viewmats[[i for i, _ in pairs]].double()).numpy()
        s, R, t = similarity(model, mine)
        spread = float(np.linalg.norm(mine - mine.mean(0), axis=1).mean())
        residual = float(np.median(np.linalg.norm(s * model @ R.T + t - mine, axis=1))) / max(spread, 1e-12)
        # camera→world rotations: the file's should be R times the model's
        turn = [_angle(views.viewmats[i, :3, :3].double().numpy().T, R @ im.cam_from_world().rotation.matrix().T)
                for i, im in pairs]
        angle = float(np.median(turn))
        if residual > FIT_TOLERANCE[0] or angle > FIT_TOLERANCE[1]:
            log.warning("%s: its %d cameras shared with the capture do not fit the capture's by a similarity "
                        "(median centre residual %.3g of their spread, rotation %.2g degrees); its points are "
                        "not used", folder, len(pairs), residual, angle)
            continue
        points = sfm_points(rec)
        xyz = s * points.xyz.double().numpy() @ R.T + t
        log.info("start points: the %d SfM points of %s (its %d cameras fit the capture's to %.2g %% of their "
                 "spread, %.2g degrees)", len(points), folder, len(pairs), 100 * residual, angle)
        return SfmPoints(xyz=torch.from_numpy(xyz).float(), rgb=points.rgb, track_length=points.track_length,
                         error=points.error), folder
    return None


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees of the rotation between rotation matrices ``a`` and ``b`` ``[3,3]``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1.0) / 2.0, -1.0, 1.0))))
