"""The training frame of a capture, from what the cameras look at and where the SfM points are.

SfM picks an arbitrary world: origin, orientation and scale depend on the mapper's initial pair. The
recipe's learning rates, the fill box ``geometry.bbox`` and the background sphere are set in the units of the
procedural and NeRF-synthetic scenes (the object about the origin, cameras about 3-4 units from it, z up), so
:func:`capture_frame` finds a similarity ``x' = s · R (x − c)`` that puts a capture the same way, from
quantities that move with the world (the frame is the same whatever similarity SfM's world is off by):

* **centre** ``c``: the weighted geometric median of the *core* of the SfM points, the points that the views
  see near their image centres (:func:`central_weight`: per point, the mean over views of ``1 − r²/2`` where
  it projects inside the image, ``r`` its offset from the principal point in half-image units; the core is
  the points with a weight of at least :data:`CORE_WEIGHT`, i.e. seen near the middle of most views): the
  object of a turntable, table or orbit capture, the middle of a forward-facing one. With fewer than :data:`MIN_CORE`
  such points (an
  untextured object in front of a textured backdrop) the centre is the cameras' look-at point (the point
  nearest, in least squares, to all optical axes) when the axes converge (:data:`MIN_SPREAD`), else the
  geometric median of all reliable points;
* **scale** ``s``: the median camera distance to the centre becomes ``data.capture.radius``;
* **rotation** ``R``: z along the cameras' mean up vector (minus the mean image y axis), x towards the first
  camera by name (its offset from the centre, perpendicular to z; its right vector when that offset is
  vertical).

The look-at point is kept as a cross-check: :meth:`CaptureFrame.diagnosis` reports both, their distance in
camera radii and how many views see the core, and the run writes it to ``capture_frame.json``.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch
import torch.nn.functional as F

from nsplat.cameras import camera_centres, look_at_point
from nsplat.data.capture import SfmPoints
from nsplat.data.views import PosedViews
from nsplat.tasks.neural.background import project
from nsplat.tasks.neural.sfm_init import reliable

#: Fewest core points for the points to place the centre.
MIN_CORE = 32
#: Central weight (:func:`central_weight`) of a core point: a backdrop point, seen near the middle of few
#: views, weighs well under it (at most 0.36 in the procedural capture), an object's 0.6-1.
CORE_WEIGHT = 0.5
#: Smallest eigenvalue of the mean projector ``I − a aᵀ`` over the optical axes ``a`` for the look-at point to
#: be trusted (0: parallel axes, a forward-facing capture; 2/3: axes from every direction).
MIN_SPREAD = 0.02
#: At most this many SfM points (every k-th by id) enter the weights.
MAX_POINTS = 20000


@dataclasses.dataclass
class CaptureFrame:
    """The similarity ``x' = scale · rotation · (x − centre)`` from a capture's world to the training frame.

    Attributes:
        centre: ``[3]`` float64 world point that becomes the origin. rotation: ``[3,3]`` float64 (rows: the
            training axes in world coordinates). scale: world → training units.
        radius: median camera distance to ``centre`` (world units).
        look_at: ``[3]`` float64 the cameras' look-at point (world). spread: its conditioning
            (:data:`MIN_SPREAD`).
        source: what placed the centre: ``points`` (the core), ``look-at`` or ``all points``.
        core: core points (of those weighed). core_extent: ``[3]`` 5th-95th percentile range of the core
            along the training axes (training units; zeros without a core).
    """

    centre: torch.Tensor
    rotation: torch.Tensor
    scale: float
    radius: float
    look_at: torch.Tensor
    spread: float
    source: str
    core: int
    core_extent: torch.Tensor

    def points(self, xyz: torch.Tensor) -> torch.Tensor:
        """World ``xyz [N,3]`` in the training frame (float32)."""
        return (self.scale * (xyz.double() - self.centre) @ self.rotation.T).float()

    def viewmats(self, viewmats: torch.Tensor) -> torch.Tensor:
        """World→camera ``viewmats [B,4,4]`` of the world as the same cameras in the training frame:
        ``[Rc·Rᵀ | s·(Rc·c + t)]`` (float32)."""
        V = viewmats.double().clone()
        V[:, :3, 3] = self.scale * (V[:, :3, :3] @ self.centre + V[:, :3, 3])
        V[:, :3, :3] = V[:, :3, :3] @ self.rotation.T
        return V.float()

    def diagnosis(self) -> dict[str, Any]:
        """The frame as JSON-ready numbers: centre, look-at point and their distance in camera radii."""
        offset = float((self.look_at - self.centre).norm()) / max(self.radius, 1e-12)
        return {"source": self.source, "centre_world": self.centre.tolist(), "look_at_world": self.look_at.tolist(),
                "look_at_offset_radii": offset, "axes_spread": self.spread, "camera_radius_world": self.radius,
                "scale": self.scale, "rotation": self.rotation.tolist(), "core_points": self.core,
                "core_extent": self.core_extent.tolist()}


def central_weight(xyz: torch.Tensor, views: PosedViews, chunk: int = 64) -> torch.Tensor:
    """``[P]`` float64: per point of ``xyz [P,3]``, the mean over ``views`` of ``1 − r²/2`` where it
    projects inside the image (0 elsewhere), ``r²`` the squared offset from the principal point in units of
    the half width and half height (so 1 at the principal point, 0 at the corners)."""
    total = torch.zeros(len(xyz), dtype=torch.float64)
    half = torch.tensor([views.width / 2.0, views.height / 2.0], dtype=torch.float64)
    for i in range(0, len(views), chunk):
        sub = views.subset(range(i, min(i + chunk, len(views))))
        uv, _, inside = project(xyz, sub)
        pp = sub.Ks[:, None, :2, 2].double()
        r2 = (((uv - pp) / half) ** 2).sum(-1)
        total += (inside.double() * (1.0 - 0.5 * r2).clamp_min(0.0)).sum(0)
    return total / len(views)


def geometric_median(x: torch.Tensor, weight: torch.Tensor, iters: int = 100) -> torch.Tensor:
    """``[3]`` float64 weighted geometric median of ``x [N,3]`` (Weiszfeld's iteration from the weighted
    mean; moves with any similarity of ``x``)."""
    x, w = x.double(), weight.double()
    m = (w[:, None] * x).sum(0) / w.sum()
    for _ in range(iters):
        d = (x - m).norm(dim=1).clamp_min(1e-12 * (1.0 + float(m.norm())))
        nxt = ((w / d)[:, None] * x).sum(0) / (w / d).sum()
        done = float((nxt - m).norm()) <= 1e-10 * (1.0 + float(m.norm()))
        m = nxt
        if done:
            break
    return m


def _axes(viewmats: torch.Tensor, centre: torch.Tensor, first: int) -> torch.Tensor:
    """``[3,3]`` rows x, y, z: z the cameras' mean up (minus the mean image-y axis), x towards camera
    ``first`` (its offset from ``centre`` perpendicular to z; its right vector when that is vertical)."""
    R = viewmats[:, :3, :3].double()
    z = -R[:, 1].mean(0)
    if float(z.norm()) < 1e-6:  # cameras rolled every way: the first camera's up
        z = -R[first, 1]
    z = F.normalize(z, dim=0)
    C0 = camera_centres(viewmats[first:first + 1].double())[0]
    x = (C0 - centre) - ((C0 - centre) @ z) * z
    if float(x.norm()) < 1e-3 * float((C0 - centre).norm() + 1e-12):
        x = R[first, 0] - (R[first, 0] @ z) * z
    x = F.normalize(x, dim=0)
    return torch.stack([x, torch.linalg.cross(z, x), z])


def capture_frame(views: PosedViews, points: SfmPoints | None, radius: float) -> CaptureFrame:
    """The training frame of a capture (module docstring).

    Args:
        views: every posed view (``viewmats [V,4,4]``, pinhole ``Ks [V,3,3]``, size, names).
        points: the SfM points (``None`` or empty: the look-at point places the centre).
        radius: the camera distance of the training frame (``data.capture.radius``).
    """
    viewmats = views.viewmats.double()
    look_at, spread = look_at_point(viewmats)
    centre, source, core, xyz_core = look_at, "look-at", 0, None
    if points is not None and len(points) > 0:
        xyz = points.xyz[reliable(points)].double()
        xyz = xyz[::max(1, math.ceil(len(xyz) / MAX_POINTS))]
        if len(xyz) > 0:
            w = central_weight(xyz, views)
            keep = w >= CORE_WEIGHT
            core = int(keep.sum())
            if core >= MIN_CORE:
                centre, source, xyz_core = geometric_median(xyz[keep], w[keep]), "points", xyz[keep]
            elif spread < MIN_SPREAD:
                centre, source = geometric_median(xyz, torch.ones(len(xyz), dtype=torch.float64)), "all points"
    dist = (camera_centres(viewmats) - centre).norm(dim=1)
    r = float(dist.median())
    if not r > 0:
        raise ValueError("cameras: every camera sits at the capture's centre; cannot set a scale")
    rotation = _axes(viewmats, centre, min(range(len(views)), key=lambda i: views.names[i]))
    scale = radius / r
    extent = torch.zeros(3, dtype=torch.float64)
    if xyz_core is not None:
        local = scale * (xyz_core - centre) @ rotation.T
        extent = torch.quantile(local, 0.95, dim=0) - torch.quantile(local, 0.05, dim=0)
    return CaptureFrame(centre=centre, rotation=rotation, scale=scale, radius=r, look_at=look_at, spread=spread,
                        source=source, core=core, core_extent=extent)
