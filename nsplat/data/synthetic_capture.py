"""A capture made here: the procedural scene photographed like a real one, then reconstructed by SfM.

:func:`render_capture` ray-traces the procedural scene (:func:`nsplat.data.procedural.make_scene`) in
front of a textured environment (a large sphere around the scene, so every pixel is covered and no
photo has a mask), through ``OPENCV`` cameras with mild lens distortion, and writes a COLMAP-layout
folder: ``images/`` (the photos), ``masks/`` (the objects' coverage, for the ground-truth baseline's visual
hull only) and ``sparse_gt/0/`` (the ground-truth cameras and poses, written by pycolmap, no points).
:func:`run_sfm` then reconstructs ``sparse/0/`` from the photos alone with pycolmap (SIFT extraction,
exhaustive matching, incremental mapping, all on the CPU) and records its time in ``sfm.json``.
:func:`ensure_capture` does both once into a cache folder keyed by the parameters.

It is the test fixture of the COLMAP path (tests/test_capture_pipeline.py) and the scene of the
measurement in docs/results.md ("Your own capture").
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import torch

from nsplat.data.procedural import camera_poses, make_scene
from nsplat.data.raytrace import shade

log = logging.getLogger(__name__)

#: Bumped whenever the output changes, so stale caches are not reused.
CAPTURE_VERSION = 1
#: SfM's focal-length prior relative to the truth (the EXIF focal length of a real photo is approximate).
FOCAL_PRIOR_ERROR = 1.05


@dataclasses.dataclass(frozen=True)
class CaptureSpec:
    """What to photograph.

    Attributes:
        seed: scene, environment and camera seed. objects: procedural objects.
        resolution: photo width = height in pixels. views: number of photos.
        radius, elevation: camera distance from the look-at point and elevation range (degrees).
        fov: horizontal field of view of the distorted camera (radians, from ``fx``).
        distortion: OPENCV ``(k1, k2, p1, p2)``.
        environment: radius of the textured environment sphere about the origin.
        supersample: rays per pixel side.
    """

    seed: int = 0
    objects: int = 4
    resolution: int = 256
    views: int = 56
    radius: float = 3.2
    elevation: tuple[float, float] = (10.0, 70.0)
    fov: float = 1.1  # 63°: a phone's main camera
    distortion: tuple[float, float, float, float] = (-0.06, 0.01, 0.0008, -0.0005)
    environment: float = 5.0
    supersample: int = 2

    def __post_init__(self) -> None:
        if self.resolution < 32:
            raise ValueError(f"resolution: expected >= 32 pixels, got {self.resolution}")
        if self.views < 8:
            raise ValueError(f"views: expected >= 8 photos, got {self.views}")
        if self.environment <= self.radius + 1.0:
            raise ValueError(f"environment: expected a radius > radius + 1 ({self.radius + 1.0}), "
                             f"got {self.environment}")

    def key(self) -> str:
        """Short hash of the spec and :data:`CAPTURE_VERSION` (the cache folder's suffix)."""
        blob = json.dumps([CAPTURE_VERSION, dataclasses.asdict(self)], sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]

    def camera(self) -> pycolmap.Camera:
        """The (shared) distorted ``OPENCV`` camera."""
        W = self.resolution
        f = 0.5 * W / math.tan(0.5 * self.fov)
        return pycolmap.Camera(camera_id=1, model="OPENCV", width=W, height=W,
                               params=[f, f, 0.5 * W, 0.5 * W, *self.distortion])


def _waves(seed: int, count: int = 192) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random 3-D plane waves of the environment texture: ``(freq [count,3], phase [count], weight [count,4])``
    (weights of one shared brightness and three colour channels)."""
    rng = np.random.default_rng([seed, 7])
    d = rng.normal(size=(count, 3))
    freq = d / np.linalg.norm(d, axis=1, keepdims=True) * np.exp(rng.uniform(np.log(8.0), np.log(240.0), (count, 1)))
    return freq, rng.uniform(0, 2 * math.pi, count), rng.normal(size=(count, 4)) / math.sqrt(count)


def environment_colour(directions: torch.Tensor, seed: int) -> torch.Tensor:
    """Albedo ``[R,3]`` in [0, 1] of the environment seen along unit ``directions [R,3]`` from its centre:
    a non-repeating sum of plane waves at many scales (texture for feature matching: mostly brightness,
    some colour) over a sky-to-ground gradient."""
    freq, phase, weight = (torch.from_numpy(a) for a in _waves(seed))
    w = torch.sin(directions @ freq.T + phase) @ weight
    base = 0.5 + 0.1 * directions[:, 2:3]
    return (base + 0.3 * torch.tanh(2.0 * w[:, :1]) + 0.12 * torch.tanh(2.0 * w[:, 1:])).clamp(0.0, 1.0)


def _rays(camera: pycolmap.Camera, viewmat: np.ndarray, supersample: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays ``(origins, dirs) [H*W*s², 3]`` through an ``s×s`` grid in each pixel of the distorted
    ``camera`` (pixel-major, as :func:`nsplat.data.raytrace.camera_rays`)."""
    s, W, H = supersample, camera.width, camera.height
    sub = (np.arange(s) + 0.5) / s
    v = (np.arange(H)[:, None, None, None] + sub[None, None, :, None]) * np.ones((1, W, 1, s))
    u = (np.arange(W)[None, :, None, None] + sub[None, None, None, :]) * np.ones((H, 1, s, 1))
    xy = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))
    cam = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    dirs = cam @ R
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return torch.from_numpy(np.broadcast_to(-R.T @ t, dirs.shape).copy()), torch.from_numpy(dirs)


def photograph(spec: CaptureSpec, viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One photo through ``spec.camera()`` at ``viewmat [4,4]``: ``(rgb [H,W,3] uint8, mask [H,W] uint8)``."""
    prims, light = make_scene(spec.seed, spec.objects)
    origins, dirs = _rays(spec.camera(), viewmat, spec.supersample)
    rgb, found = shade(prims, light, origins, dirs)
    # Where a ray leaves the scene it meets the environment sphere |x| = R (the camera is inside it).
    b = (origins * dirs).sum(-1)
    t = -b + torch.sqrt(b * b - (origins * origins).sum(-1) + spec.environment ** 2)
    env = environment_colour((origins + t[:, None] * dirs) / spec.environment, spec.seed)
    rgb = torch.where(found[:, None], rgb, env)
    n = spec.supersample ** 2
    H = W = spec.resolution
    colour = rgb.reshape(H, W, n, 3).mean(2).numpy()
    cover = found.double().reshape(H, W, n).mean(-1).numpy()
    return ((colour * 255.0 + 0.5).clip(0, 255).astype(np.uint8),
            (cover * 255.0 + 0.5).clip(0, 255).astype(np.uint8))


def image_name(i: int) -> str:
    """File name of photo ``i``."""
    return f"im_{i:03d}.png"


def render_capture(spec: CaptureSpec, out_dir: Path) -> pycolmap.Reconstruction:
    """Write ``images/``, ``masks/`` and the ground-truth model ``sparse_gt/0/`` of ``spec`` under ``out_dir``.

    Returns:
        The ground-truth reconstruction (one ``OPENCV`` camera, ``spec.views`` posed images, no points).
    """
    out_dir = Path(out_dir)
    for sub in ("images", "masks", "sparse_gt/0"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
    viewmats = camera_poses(spec.views, spec.radius, spec.elevation, np.random.default_rng([spec.seed, 2])).numpy()
    rec = pycolmap.Reconstruction()
    camera = spec.camera()
    rec.add_camera_with_trivial_rig(camera)
    for i, V in enumerate(viewmats):
        rgb, mask = photograph(spec, V)
        iio.imwrite(out_dir / "images" / image_name(i), rgb)
        iio.imwrite(out_dir / "masks" / image_name(i), mask)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(V[:3, :3]), V[:3, 3])
        image = pycolmap.Image(image_id=i + 1, name=image_name(i), camera_id=camera.camera_id)
        rec.add_image_with_trivial_frame(image, pose)
    rec.write_binary(str(out_dir / "sparse_gt" / "0"))
    return rec


def run_sfm(scene: Path, focal_prior: float, threads: int = 1) -> dict[str, float]:
    """Reconstruct ``scene/sparse/0`` from ``scene/images`` with pycolmap on the CPU: SIFT features (one
    shared ``OPENCV`` camera), exhaustive matching, incremental mapping with the intrinsics held at the
    prior (``focal_prior`` pixels, as a photo's EXIF focal length gives it; principal point at the image
    centre, no distortion), then one global bundle adjustment that refines focal length and distortion.

    Why two steps: at these photo sizes, with a 63° lens and mostly distant texture, refining the
    intrinsics during incremental mapping (COLMAP's default) drifted to a focal length 0.65-1.9x the
    truth and registered at most 3 images in every setting we tried; with the prior held, every image
    registered (docs/capture.md).

    Returns:
        Seconds per stage and in total, the registered image count, the point count and the mean
        reprojection error (also written to ``scene/sfm.json``). Raises ``RuntimeError`` when mapping
        registers no model.
    """
    scene = Path(scene)
    db = scene / "sfm" / "database.db"
    db.parent.mkdir(parents=True, exist_ok=True)
    db.unlink(missing_ok=True)
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions(num_threads=threads)
    extraction.sift.peak_threshold = 0.004  # small, low-contrast photos: keep weaker blobs (COLMAP: 0.0067)
    W, H = iio.imread(next((scene / "images").iterdir())).shape[1::-1]
    prior = f"{focal_prior},{focal_prior},{W / 2},{H / 2},0,0,0,0"
    pycolmap.extract_features(db, scene / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=pycolmap.ImageReaderOptions(camera_model="OPENCV", camera_params=prior),
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    times["extract_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    pycolmap.match_exhaustive(db, matching_options=pycolmap.FeatureMatchingOptions(num_threads=threads),
                              device=pycolmap.Device.cpu)
    times["match_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    options = pycolmap.IncrementalPipelineOptions(num_threads=threads, random_seed=0, multiple_models=False)
    # COLMAP's defaults assume megapixel photos with near structure: a small photo has fewer inliers, and
    # most of this scene's texture is the environment, seen with little parallax.
    options.mapper.init_min_num_inliers = 50
    options.mapper.init_min_tri_angle = 4.0
    options.ba_refine_focal_length = options.ba_refine_extra_params = options.ba_refine_principal_point = False
    models = pycolmap.incremental_mapping(db, scene / "images", scene / "sfm", options=options)
    if not models:
        raise RuntimeError(f"{scene}: pycolmap's incremental mapping registered no model")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    times["map_s"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    ba = pycolmap.BundleAdjustmentOptions(refine_focal_length=True, refine_extra_params=True,
                                          refine_principal_point=False, print_summary=False)
    ba.ceres.solver_options.num_threads = threads
    pycolmap.bundle_adjustment(rec, ba)
    times["refine_s"] = time.perf_counter() - t3
    times["total_s"] = time.perf_counter() - t0
    (scene / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(scene / "sparse" / "0"))
    out = {**times, "registered": rec.num_reg_images(), "images": len(list((scene / "images").iterdir())),
           "points": rec.num_points3D(), "mean_reprojection_error_px": rec.compute_mean_reprojection_error()}
    (scene / "sfm.json").write_text(json.dumps(out, indent=1))
    return out


def ensure_capture(spec: CaptureSpec, cache_dir: Path, threads: int = 1) -> Path:
    """Folder of the capture for ``spec`` under ``cache_dir`` (photos, masks, ``sparse_gt/0``, ``sparse/0``,
    ``sfm.json``), made on first use in a temporary sibling that is renamed into place. SfM's focal-length
    prior is the true focal length times :data:`FOCAL_PRIOR_ERROR` (an EXIF value is approximate)."""
    cache_dir = Path(cache_dir)
    target = cache_dir / f"capture-s{spec.seed}-r{spec.resolution}-{spec.key()}"
    if (target / "sfm.json").is_file():
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    log.info("photographing the procedural scene and running SfM into %s", target)
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=cache_dir))
    try:
        render_capture(spec, tmp)
        run_sfm(tmp, spec.camera().focal_length_x * FOCAL_PRIOR_ERROR, threads)
        (tmp / "spec.json").write_text(json.dumps({"version": CAPTURE_VERSION, **dataclasses.asdict(spec)}, indent=1))
        shutil.rmtree(tmp / "sfm", ignore_errors=True)  # the database and mapper output: sparse/0 holds the model
        os.chmod(tmp, 0o755)
        try:
            os.replace(tmp, target)
        except OSError:
            if not (target / "sfm.json").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target
