"""Task ``neural`` on a user's own capture (``data.source: colmap`` or ``transforms``, docs/capture.md).

The COLMAP folder (:func:`nsplat.data.colmap.load_colmap`) or nerfstudio / instant-ngp ``transforms.json``
folder (:func:`nsplat.data.transforms_json.load_transforms`) at ``data.root`` is loaded once per process
(undistorted, downscaled, every 8th image by name held out as ``test``) and prepared for training:

* **validation split**: of the training images, every ``val_every``-th from the ``val_every // 2``-th is
  held out as ``val`` (for model selection: the test views are never looked at before the end);
* **world frame** (``normalize``): SfM's world has an arbitrary origin, orientation and scale, while the
  learning rates, ``geometry.bbox`` and the default sizes are in the units of the procedural and
  NeRF-synthetic scenes (the object about the origin, cameras about 3-4 units from it, z up). The world is
  moved by the similarity of :func:`nsplat.tasks.neural.frame.capture_frame`: the centre is where the SfM
  points that the views see near their image centres are (else the cameras' look-at point), the median
  camera distance to it becomes ``radius`` and z the cameras' mean up direction (images are unchanged; the
  SfM points move with it). The frame is the same whatever similarity SfM's world is off by;
* **near/far** (``near_far``): the render's clipping planes from the SfM points' depths
  (:func:`nsplat.tasks.neural.background.depth_range`: half the smallest depth, twice the farthest reach;
  depths under :data:`STRAY_DEPTH` camera distances are stray points, passed over);
* **points of a ``transforms.json`` folder** (:func:`capture_points`): the file has none, so with
  ``geometry.init: auto`` (and neither ``ply_file_path`` nor ``data.capture.masks``) they come from a COLMAP model
  beside the file, else are triangulated from the training photos with the file's poses
  (:mod:`nsplat.data.triangulate`, cached); from there they are the capture's SfM points and flow as a COLMAP
  capture's do (the frame's centre, near/far, the background sphere, the start: :func:`start_kind`).
"""
from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import torch

from nsplat.cameras import camera_centres
from nsplat.config import ConfigError, to_dict
from nsplat.data.capture import SfmPoints, cache_folder
from nsplat.data.colmap import load_colmap
from nsplat.data.paths import resolve
from nsplat.data.transforms_json import load_transforms, point_cloud_path
from nsplat.data.triangulate import cached_triangulation, colmap_points_beside
from nsplat.data.views import PosedViews
from nsplat.errors import DataError
from nsplat.tasks.neural.background import depth_range, fit_sphere
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.frame import CaptureFrame, capture_frame
from nsplat.tasks.neural.sfm_init import reliable

log = logging.getLogger(__name__)


@dataclasses.dataclass
class PreparedCapture:
    """A capture split three ways in the training world frame.

    Attributes:
        splits: ``train``, ``val``, ``test`` :class:`PosedViews` (CPU).
        points: the SfM points (``xyz`` in the training frame), or ``None`` when the model has none.
        frame: the capture's frame as found (:class:`~nsplat.tasks.neural.frame.CaptureFrame`, in the
            capture's world; its :meth:`~CaptureFrame.diagnosis` goes to the run's ``capture_frame.json``).
        normalized: whether the training frame is ``frame``'s (``data.capture.normalize``), else the
            capture's world itself.
        ply: the point cloud a ``transforms.json`` names in ``ply_file_path`` (in the capture's world), or
            ``None``.
        origin: where ``points`` come from: ``model`` (the COLMAP capture's own), ``triangulated`` (from the
            training photos of a ``transforms.json`` folder), the COLMAP model folder beside such a file, or ``""``
            (none); with ``note``, why a ``transforms.json`` folder has none (a sentence, or ``""``).
    """

    splits: dict[str, PosedViews]
    points: SfmPoints | None
    frame: CaptureFrame
    normalized: bool
    ply: Path | None = None
    origin: str = ""
    note: str = ""

    def to_training(self, xyz: torch.Tensor) -> torch.Tensor:
        """World points ``xyz [N,3]`` of the capture in the training frame (float32)."""
        return self.frame.points(xyz) if self.normalized else xyz.float()

    def to_training_viewmats(self, viewmats: torch.Tensor) -> torch.Tensor:
        """World→camera ``viewmats [B,4,4]`` of the capture's world in the training frame (float32)."""
        return self.frame.viewmats(viewmats) if self.normalized else viewmats.float()

    def centre(self) -> tuple[torch.Tensor, float]:
        """``(centre [3] float64, radius)``: the scene centre and median camera distance to it in the
        training frame (the origin and ``data.capture.radius`` when normalised)."""
        if self.normalized:
            return torch.zeros(3, dtype=torch.float64), self.frame.radius * self.frame.scale
        return self.frame.centre, self.frame.radius


_CACHE: dict[str, PreparedCapture] = {}


def prepare(cfg: Config) -> PreparedCapture:
    """The configured capture, loaded and prepared once per process (keyed by ``cfg.data`` and whether
    ``geometry.init`` is ``auto``, which may look for points: :func:`wants_points`)."""
    key = json.dumps([to_dict(cfg.data), cfg.geometry.init == "auto"], sort_keys=True)
    if key in _CACHE:
        return _CACHE[key]
    c = cfg.data.capture
    root, cache = resolve(cfg.data.root or ""), resolve(c.cache_dir) if c.cache_dir else None
    ply = None
    if cfg.data.source == "transforms":
        cap = load_transforms(root, downscale=c.downscale, holdout_every=c.holdout_every, file=c.file,
                              cache_dir=cache, masks=c.masks)
        ply = point_cloud_path(root, c.file)
    else:
        cap = load_colmap(root, downscale=c.downscale, holdout_every=c.holdout_every, images=c.images,
                          sparse=c.sparse, masks=c.masks, cache_dir=cache)
    n = len(cap.train)
    val_idx = list(range(c.val_every // 2, n, c.val_every))
    if not val_idx or len(val_idx) == n:
        raise ConfigError(f"data.capture.val_every: {c.val_every} leaves no validation or no training view "
                          f"among the {n} training images")
    splits = {"train": cap.train.subset([i for i in range(n) if i not in val_idx]),
              "val": cap.train.subset(val_idx), "test": cap.test}
    origin, note = ("model" if cap.points is not None else ""), ""
    if ply is None and wants_points(cfg):
        cap.points, origin, note = capture_points(cfg, root, splits["train"])
    V = len(cap.train) + len(cap.test)   # every camera, without pixels (channels 0)
    every = PosedViews(images=torch.empty(V, cap.train.height, cap.train.width, 0),
                       viewmats=torch.cat([cap.train.viewmats, cap.test.viewmats]),
                       Ks=torch.cat([cap.train.Ks, cap.test.Ks]), names=cap.train.names + cap.test.names)
    try:
        frame = capture_frame(every, cap.points, c.radius)
    except ValueError as exc:
        raise DataError(f"{root}: {exc}") from exc
    prep = PreparedCapture(splits=splits, points=cap.points, frame=frame, normalized=c.normalize, ply=ply,
                           origin=origin, note=note)
    if c.normalize:
        prep.splits = {k: dataclasses.replace(v, viewmats=frame.viewmats(v.viewmats)) for k, v in splits.items()}
        if cap.points is not None:
            prep.points = dataclasses.replace(cap.points, xyz=frame.points(cap.points.xyz))
    _CACHE.clear()
    _CACHE[key] = prep
    return prep


#: Long side in pixels below which the photos are triangulated at a finer downscale than they train at (the
#: largest whole ``data.capture.downscale`` that keeps at least this many pixels).
TRIANGULATION_SIZE = 640
#: Fewest points a triangulation must find to start from them (else the common-view start, with a warning).
MIN_TRIANGULATED = 64


def wants_points(cfg: Config) -> bool:
    """Whether :func:`prepare` finds points for a ``transforms.json`` folder whose file names no ``ply_file_path``
    (:func:`capture_points`): with ``geometry.init: auto`` and no ``data.capture.masks`` (the hull starts)."""
    return cfg.data.source == "transforms" and cfg.geometry.init == "auto" and not cfg.data.capture.masks


def capture_points(cfg: Config, root: Path, train: PosedViews) -> tuple[SfmPoints | None, str, str]:
    """``(points, origin, note)`` of a ``transforms.json`` folder at ``root`` in the file's world: the SfM points
    of a COLMAP model beside it (:func:`~nsplat.data.triangulate.colmap_points_beside`; ``origin`` its folder),
    else those triangulated from the ``train`` photos with their poses held, read at a finer downscale when they
    train under :data:`TRIANGULATION_SIZE` pixels (:func:`~nsplat.data.triangulate.cached_triangulation`, cached
    beside the undistorted photos; ``origin`` ``triangulated``); ``(None, "", note)`` with a warning when the
    triangulation fails or finds fewer than :data:`MIN_TRIANGULATED` points. ``train``: the training views
    (``images [V,H,W,3]``, world→camera ``viewmats [V,4,4]``, pinhole ``Ks [V,3,3]``) in the file's world."""
    beside = colmap_points_beside(root, train)
    if beside is not None:
        return beside[0], str(beside[1]), ""
    c = cfg.data.capture
    cache_dir = resolve(c.cache_dir) if c.cache_dir else None
    cache = cache_folder(root, cache_dir, c.downscale).parent / "triangulated"
    finer = max(1, c.downscale * max(train.width, train.height) // TRIANGULATION_SIZE)
    if finer < c.downscale:  # the same training photos, larger: more features, finer rays
        loader, level = logging.getLogger("nsplat.data.capture"), logging.getLogger("nsplat.data.capture").level
        loader.setLevel(logging.ERROR)  # the skipped frames were named once, by the first load
        try:
            cap = load_transforms(root, downscale=finer, holdout_every=c.holdout_every, file=c.file,
                                  cache_dir=cache_dir)
            index = {name: i for i, name in enumerate(cap.train.names)}
            train = cap.train.subset([index[name] for name in train.names])
        except (DataError, KeyError) as exc:  # e.g. a folder that ships only its images_<d> copies
            log.info("triangulating at the training resolution: the photos at downscale %d: %s", finer, exc)
        finally:
            loader.setLevel(level)
    try:
        points = cached_triangulation(train, cache, threads=torch.get_num_threads())
    except (RuntimeError, ValueError, OSError) as exc:
        note = f"the triangulation from the training photos failed ({' '.join(str(exc).split())})"
    else:
        if len(points) >= MIN_TRIANGULATED:
            return points, "triangulated", ""
        note = (f"the triangulation from the {len(train)} training photos found {len(points)} points (fewer than "
                f"{MIN_TRIANGULATED}: too little texture, or poses that do not match the photos)")
    log.warning("%s: %s; starting from random points in the cameras' common view", root, note)
    return None, "", note


def start_kind(cfg: Config) -> str:
    """What ``geometry.init`` starts from (:func:`nsplat.tasks.neural.starts.initial_geometry`), ``auto`` resolved
    (see its doc): ``hull``, ``ply``, ``random``, ``sfm`` (a COLMAP capture's points, or those of the model beside
    a ``transforms.json``), ``capture_ply`` (the point cloud a ``transforms.json`` names), ``triangulated``
    (points triangulated from a ``transforms.json`` folder's photos with its poses: :func:`capture_points`) or
    ``view_fill`` (random points in the training cameras' common view, when the triangulation found too few)."""
    if cfg.geometry.init != "auto":
        return cfg.geometry.init
    if cfg.data.source == "colmap":
        return "sfm"
    if cfg.data.source != "transforms":
        return "hull"
    prep = prepare(cfg)
    if prep.ply is not None:
        return "capture_ply"
    if cfg.data.capture.masks:
        return "hull"
    if prep.points is None:
        return "view_fill"
    return "triangulated" if prep.origin == "triangulated" else "sfm"


def to_training_frame(cfg: Config, viewmats: torch.Tensor) -> torch.Tensor:
    """Cameras ``viewmats [B,4,4]`` given in the data's own world (the COLMAP model's, ``transforms.json``'s,
    the NeRF-synthetic scene's) moved into the training frame (a capture's normalisation; else as given)."""
    if not cfg.data.is_capture():
        return viewmats.float()
    return prepare(cfg).to_training_viewmats(viewmats)


def capture_views(cfg: Config, split: str, device: torch.device) -> PosedViews:
    """One split (``train``, ``val`` or ``test``) of the configured capture on ``device``."""
    return prepare(cfg).splits[split].to(device)


#: SfM points nearer than this many camera distances to a camera that sees them do not set the near plane:
#: one two-view point of a lego SfM run sat 5e-8 camera distances in front of a camera.
STRAY_DEPTH = 0.01


def with_capture_render(cfg: Config) -> Config:
    """``cfg`` with ``render.near/far`` set when ``data.capture.near_far`` applies to a capture:
    from the SfM points' depths (:func:`nsplat.tasks.neural.background.depth_range`) when the model has points, else,
    with a background sphere, ``near`` half the smallest camera-to-sphere distance and ``far`` twice the
    largest; otherwise ``cfg`` itself. Without a near plane the sphere's points beside a camera (depth
    near 0) would be splatted over the whole image."""
    if not cfg.data.is_capture() or not cfg.data.capture.near_far:
        return cfg
    prep = prepare(cfg)
    bg = cfg.geometry.background
    centres = camera_centres(prep.splits["train"].viewmats.double())
    if prep.points is not None and len(prep.points) > 0:
        scene, radius = prep.centre()
        far_radius = radius
        if bg.model == "sphere":
            centre, sphere = background_sphere(cfg)
            far_radius = max(sphere + float((centre - scene).norm()), radius)
        near, far = depth_range(prep.points.xyz, prep.splits["train"], scene, far_radius,
                                min_depth=STRAY_DEPTH * radius)
    elif bg.model == "sphere":
        centre, sphere = background_sphere(cfg)
        dist = (centres - centre).norm(dim=1)
        near, far = 0.5 * (sphere - float(dist.max())), 2.0 * (sphere + float(dist.max()))
        if near <= 0:
            raise ConfigError(f"geometry.background.radius: the sphere (radius {sphere:.4g}) must enclose every "
                              f"camera (up to {float(dist.max()):.4g} from its centre)")
    else:
        return cfg
    return dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, near=near, far=far))


#: SfM points farther than this many camera distances from the scene centre are the background.
FAR_POINTS = 1.5
#: Fewest background points to fit the sphere to.
MIN_FAR_POINTS = 20
#: The background sphere's radius (camera distances) when ``geometry.background.radius`` is null and there are no
#: points to fit it to.
FALLBACK_RADIUS = 3.0


def scene_points(cfg: Config) -> SfmPoints | None:
    """The SfM points within :data:`FAR_POINTS` camera distances of the scene centre (the scene;
    the rest are the background), or ``None`` when the model has no points.

    Used with ``geometry.sfm.background_points: false`` (measured in docs/results.md)."""
    points = prepare(cfg).points
    if points is None:
        return None
    centre, radius = prepare(cfg).centre()
    near = (points.xyz.double() - centre).norm(dim=1) <= FAR_POINTS * radius
    return dataclasses.replace(points, xyz=points.xyz[near], rgb=points.rgb[near],
                               track_length=points.track_length[near], error=points.error[near])


def background_sphere(cfg: Config) -> tuple[torch.Tensor, float]:
    """``(centre [3] float64, radius)`` of the background sphere in the training frame.

    ``geometry.background.radius`` (camera distances) and ``centre`` when given. Otherwise from the
    reliable SfM points farther than :data:`FAR_POINTS` camera distances from the scene centre
    (the background): the least-squares sphere through them (:func:`nsplat.tasks.neural.background.fit_sphere`; with a
    given centre, their median distance from it), as long as it encloses every camera with a margin of
    half a camera distance; else, or with fewer than :data:`MIN_FAR_POINTS` such points, a sphere about the
    scene centre (or the given centre) through the 98th percentile of all reliable points' distances,
    times 1.05, and at least 1.5 camera distances.
    """
    bg = cfg.geometry.background
    views = prepare(cfg).splits["train"].viewmats
    scene, radius = prepare(cfg).centre()
    centre = scene if bg.centre is None else torch.tensor(bg.centre, dtype=torch.float64)
    if bg.radius is not None:
        return centre, bg.radius * radius
    points = prepare(cfg).points
    if points is None or len(points) == 0:  # e.g. a transforms.json folder whose triangulation found too few
        log.warning("geometry.background.radius: null, but there are no points to fit the background to: a sphere "
                    "of %.1f camera distances about the scene centre", FALLBACK_RADIUS)
        return centre, FALLBACK_RADIUS * radius
    s = cfg.geometry.sfm
    xyz = points.xyz[reliable(points, s.min_track, s.max_error)].double()
    far = xyz[(xyz - scene).norm(dim=1) > FAR_POINTS * radius]
    if len(far) >= MIN_FAR_POINTS:
        c, r = fit_sphere(far) if bg.centre is None else (centre, float((far - centre).norm(dim=1).median()))
        if r - float((camera_centres(views.double()) - c).norm(dim=1).max()) > 0.5 * radius:
            return c, r
    dist = (xyz - centre).norm(dim=1)
    return centre, max(1.05 * float(torch.quantile(dist, 0.98)), FAR_POINTS * radius)
