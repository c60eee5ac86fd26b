"""Background model for unmasked photos: surfels on a far sphere around the scene.

A photo of a real scene has something behind the object in every pixel. NeRF-synthetic images are
masked and composited on a constant colour; a capture is not, so the stage-1 fitter would otherwise pull
object points out into the background to explain it. :func:`sphere_background` places surfels evenly
(a Fibonacci lattice) on a sphere of radius ``R`` about the scene centre, facing inwards, keeps those that
some training camera sees, and colours each with the mean of the training pixels it projects to. They are
ordinary points of the scene: the stage-1 fitter and the stage-2 features learn them like any other, so
the same model serves both stages (a background feature map given to the U-Net would exist in stage 2
only). Why this one, measured: docs/results.md ("Your own capture").

:func:`fit_sphere` gives the sphere through the distant SfM points; :func:`depth_range` the near/far planes from
the SfM points' depths.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from nsplat.cameras import camera_centres
from nsplat.data.views import PosedViews


def fit_sphere(points: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Least-squares sphere through ``points [P,3]`` (P >= 4): ``(centre [3] float64, radius)``, from the
    linear form ``|x|² = 2 c·x + (r² − |c|²)``."""
    x = points.double()
    A = torch.cat([2.0 * x, torch.ones(len(x), 1, dtype=torch.float64)], 1)
    sol = torch.linalg.lstsq(A, (x * x).sum(1, keepdim=True)).solution[:, 0]
    centre = sol[:3]
    return centre, float(torch.sqrt(sol[3] + centre @ centre))


def fibonacci_sphere(count: int) -> torch.Tensor:
    """``[count,3]`` float64 unit vectors evenly spread over the sphere (Fibonacci lattice)."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = (1.0 - z * z).clamp_min(0).sqrt()
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], 1)


def project(points: torch.Tensor, views: PosedViews) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(uv [V,N,2], depth [V,N], inside [V,N] bool)``: pixel positions of world ``points [N,3]`` in every
    view, their camera depth, and whether they land in front of the camera and inside the image."""
    V = views.viewmats.double()
    cam = points.double() @ V[:, :3, :3].transpose(1, 2) + V[:, None, :3, 3]
    depth = cam[..., 2]
    pix = cam @ views.Ks.double().transpose(1, 2)
    uv = pix[..., :2] / depth.clamp_min(1e-12)[..., None]
    inside = (depth > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= views.width) & (uv[..., 1] >= 0) \
        & (uv[..., 1] <= views.height)
    return uv, depth, inside


def sphere_background(views: PosedViews, centre: torch.Tensor, radius: float, count: int,
                      min_views: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Background surfels on the sphere ``|x − centre| = radius``.

    Args:
        views: the training views (``images [V,H,W,3]``); points none of them sees are dropped.
        centre: ``[3]`` sphere centre. radius: sphere radius (world units).
        count: lattice points on the whole sphere (the kept ones are those seen).
        min_views: keep points seen by at least this many views.

    Returns:
        ``(means [M,3], normals [M,3] (inwards), colours [M,3], spacing [M])``, float32: colours are the
        mean of the bilinearly sampled training pixels the point projects to; spacing is the lattice's.
    """
    if count < 4:
        raise ValueError(f"count: expected >= 4 background points, got {count}")
    if radius <= 0:
        raise ValueError(f"radius: expected > 0, got {radius}")
    dirs = fibonacci_sphere(count)
    means = centre.double() + radius * dirs
    uv, _, inside = project(means, views)
    grid = (uv / torch.tensor([views.width, views.height], dtype=torch.float64) * 2.0 - 1.0).float()
    img = views.images.permute(0, 3, 1, 2).float()              # [V,3,H,W]
    samples = F.grid_sample(img, grid[:, :, None, :], mode="bilinear", padding_mode="border",
                            align_corners=False)[:, :, :, 0]    # [V,3,N]
    w = inside.float()
    seen = w.sum(0)
    keep = seen >= min_views
    if not bool(keep.any()):
        raise ValueError(f"background: no point of the sphere (radius {radius:.4g}) is seen by {min_views} views")
    colours = (samples * w[:, None, :]).sum(0).T / seen.clamp_min(1.0)[:, None]
    spacing = torch.full((count,), radius * math.sqrt(4.0 * math.pi / count))
    return means[keep].float(), (-dirs[keep]).float(), colours[keep].clamp(0.0, 1.0), spacing[keep]


def depth_range(points: torch.Tensor, views: PosedViews, centre: torch.Tensor, far_radius: float,
                margin: float = 0.5, min_depth: float = 0.0) -> tuple[float, float]:
    """``(near, far)`` clipping planes from the SfM ``points [P,3]``: ``near`` is ``margin`` times the
    smallest depth of a point inside any of ``views`` (not a percentile: a small object in front of a
    well-textured background may own well under 1 % of the points), depths under ``min_depth`` passed over
    (a stray two-view point triangulated on a camera centre, 1e-7 camera distances in front of it, would put
    the near plane there, where the background surfels beside that camera overflow the projection); ``far``
    is twice the farthest camera-to-point distance that a background sphere of radius ``far_radius`` about
    the scene ``centre [3]`` can reach."""
    _, depth, inside = project(points, views)
    d = depth[inside & (depth >= min_depth)]
    if d.numel() == 0:
        raise ValueError(f"SfM points: none projects into any view at a depth of at least {min_depth:.3g}; "
                         f"cannot set near/far")
    near = margin * float(d.min())
    reach = float((camera_centres(views.viewmats.double()) - centre.double()).norm(dim=1).max()) + far_radius
    return near, 2.0 * max(reach, float(d.max()))
