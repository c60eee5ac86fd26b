"""Task ``neural`` on a user's own capture (``data.source: colmap`` or ``transforms``, docs/capture.md).

The COLMAP folder (:func:`nsplat.data.colmap.load_colmap`) or nerfstudio / instant-ngp ``transforms.json``
folder (:func:`nsplat.data.transforms_json.load_transforms`) at ``data.root`` is loaded once per process
(undistorted, downscaled, every 8th image by name held out as ``test``) and prepared for training:

* **validation split**: of the training images, every ``val_every``-th from the ``val_every // 2``-th is
  held out as ``val`` (for model selection: the test views are never looked at before the end);
* **world frame** (``normalize``): SfM's world has an arbitrary origin and scale, while the learning rates
  and default sizes are in the units of the procedural and NeRF-synthetic scenes (cameras about 3-4 units
  from the object). The world is moved so that the point nearest to all optical axes is the origin and
  scaled so that the median camera distance to it is ``radius`` (a similarity: images are unchanged);
  the SfM points move with it;
* **near/far** (``near_far``): the render's clipping planes from the SfM points' depths
  (:func:`nsplat.tasks.neural.background.depth_range`: half the smallest depth, twice the farthest reach).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import torch

from nsplat.cameras import camera_centres
from nsplat.config import ConfigError, to_dict
from nsplat.data.capture import SfmPoints
from nsplat.data.colmap import load_colmap
from nsplat.data.transforms_json import load_transforms, point_cloud_path
from nsplat.data.paths import resolve
from nsplat.data.views import PosedViews
from nsplat.tasks.neural.background import depth_range, fit_sphere, scene_frame
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.sfm_init import reliable


@dataclasses.dataclass
class PreparedCapture:
    """A capture split three ways in the training world frame.

    Attributes:
        splits: ``train``, ``val``, ``test`` :class:`PosedViews` (CPU).
        points: the SfM points (``xyz`` in the training frame), or ``None`` when the model has none.
        centre, scale: the training frame is ``x' = scale · (x − centre)`` of the capture's world
            (``centre [3]`` float64; zeros and 1 without ``normalize``).
        ply: the point cloud a ``transforms.json`` names in ``ply_file_path`` (in the capture's world), or
            ``None``.
    """

    splits: dict[str, PosedViews]
    points: SfmPoints | None
    centre: torch.Tensor
    scale: float
    ply: Path | None = None


_CACHE: dict[str, PreparedCapture] = {}


def moved_viewmats(viewmats: torch.Tensor, centre: torch.Tensor, s: float) -> torch.Tensor:
    """Cameras ``viewmats [B,4,4]`` in the frame ``x' = s (x − centre)``: ``[R | s (R·centre + t)]`` (float32)."""
    V = viewmats.double().clone()
    V[:, :3, 3] = s * (V[:, :3, :3] @ centre.double() + V[:, :3, 3])
    return V.float()


def _transform(views: PosedViews, centre: torch.Tensor, s: float) -> PosedViews:
    """``views`` in the frame ``x' = s (x − centre)`` (camera units scale too)."""
    return dataclasses.replace(views, viewmats=moved_viewmats(views.viewmats, centre, s))


def prepare(cfg: Config) -> PreparedCapture:
    """The configured capture, loaded and prepared once per process (keyed by ``cfg.data``)."""
    key = json.dumps(to_dict(cfg.data), sort_keys=True)
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
    points = cap.points
    centre, s = torch.zeros(3, dtype=torch.float64), 1.0
    if c.normalize:
        centre, radius = scene_frame(torch.cat([cap.train.viewmats, cap.test.viewmats]))
        s = c.radius / radius
        splits = {k: _transform(v, centre, s) for k, v in splits.items()}
        if points is not None:
            points = dataclasses.replace(points, xyz=(s * (points.xyz.double() - centre)).float())
    _CACHE.clear()
    _CACHE[key] = PreparedCapture(splits=splits, points=points, centre=centre, scale=s, ply=ply)
    return _CACHE[key]


def to_training_frame(cfg: Config, viewmats: torch.Tensor) -> torch.Tensor:
    """Cameras ``viewmats [B,4,4]`` given in the data's own world (the COLMAP model's, ``transforms.json``'s,
    the NeRF-synthetic scene's) moved into the training frame (a capture's normalisation; else as given)."""
    if not cfg.data.is_capture():
        return viewmats.float()
    prep = prepare(cfg)
    return moved_viewmats(viewmats, prep.centre, prep.scale)


def capture_views(cfg: Config, split: str, device: torch.device) -> PosedViews:
    """One split (``train``, ``val`` or ``test``) of the configured capture on ``device``."""
    return prepare(cfg).splits[split].to(device)


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
        _, radius = scene_frame(prep.splits["train"].viewmats)
        far_radius = radius
        if bg.model == "sphere":
            centre, sphere = background_sphere(cfg)
            far_radius = max(sphere + float(centre.norm()), radius)
        near, far = depth_range(prep.points.xyz, prep.splits["train"], far_radius)
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


#: SfM points farther than this many camera distances from the look-at point are the background.
FAR_POINTS = 1.5
#: Fewest background points to fit the sphere to.
MIN_FAR_POINTS = 20


def scene_points(cfg: Config) -> SfmPoints | None:
    """The SfM points within :data:`FAR_POINTS` camera distances of the cameras' look-at point (the scene;
    the rest are the background), or ``None`` when the model has no points.

    Used with ``geometry.sfm.background_points: false`` (measured in docs/results.md)."""
    points = prepare(cfg).points
    if points is None:
        return None
    look_at, radius = scene_frame(prepare(cfg).splits["train"].viewmats)
    near = (points.xyz.double() - look_at).norm(dim=1) <= FAR_POINTS * radius
    return dataclasses.replace(points, xyz=points.xyz[near], rgb=points.rgb[near],
                               track_length=points.track_length[near], error=points.error[near])


def background_sphere(cfg: Config) -> tuple[torch.Tensor, float]:
    """``(centre [3] float64, radius)`` of the background sphere in the training frame.

    ``geometry.background.radius`` (camera distances) and ``centre`` when given. Otherwise from the
    reliable SfM points farther than :data:`FAR_POINTS` camera distances from the cameras' look-at point
    (the background): the least-squares sphere through them (:func:`nsplat.tasks.neural.background.fit_sphere`; with a
    given centre, their median distance from it), as long as it encloses every camera with a margin of
    half a camera distance; else, or with fewer than :data:`MIN_FAR_POINTS` such points, a sphere about the
    look-at point (or the given centre) through the 98th percentile of all reliable points' distances,
    times 1.05, and at least 1.5 camera distances.
    """
    bg = cfg.geometry.background
    views = prepare(cfg).splits["train"].viewmats
    look_at, radius = scene_frame(views)
    centre = look_at if bg.centre is None else torch.tensor(bg.centre, dtype=torch.float64)
    if bg.radius is not None:
        return centre, bg.radius * radius
    points = prepare(cfg).points
    if points is None or len(points) == 0:
        raise ConfigError("geometry.background.radius: null needs SfM points (the model's points3D is empty); "
                          "give a multiple of the camera distance")
    s = cfg.geometry.sfm
    xyz = points.xyz[reliable(points, s.min_track, s.max_error)].double()
    far = xyz[(xyz - look_at).norm(dim=1) > FAR_POINTS * radius]
    if len(far) >= MIN_FAR_POINTS:
        c, r = fit_sphere(far) if bg.centre is None else (centre, float((far - centre).norm(dim=1).median()))
        if r - float((camera_centres(views.double()) - c).norm(dim=1).max()) > 0.5 * radius:
            return c, r
    dist = (xyz - centre).norm(dim=1)
    return centre, max(1.05 * float(torch.quantile(dist, 0.98)), FAR_POINTS * radius)
