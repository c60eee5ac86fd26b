"""A small analytic ray tracer in PyTorch, independent of the splatting op.

It renders scenes of spheres, boxes (rotated about the world z axis) and finite planes (rectangles)
with procedural textures, Lambertian shading under one directional light plus ambient light, and
hard shadows. It exists to make ground-truth images for the procedural test scene
(:mod:`nsplat.data.procedural`), so it shares nothing with the op but the camera convention:
OpenCV world→camera ``viewmat`` (x right, y down, z forward), pixel intrinsics ``K``, pixel centres
at ``(i + 0.5, j + 0.5)``.

Everything is float64 on the CPU; a 64×64 image with 2×2 supersampling takes a few milliseconds.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Literal

import torch

Texture = Literal["solid", "checker", "stripes", "rings"]
_INF = math.inf


@dataclasses.dataclass(frozen=True)
class Material:
    """Procedural albedo in the primitive's local frame.

    Attributes:
        texture: ``solid`` (colour ``a``), ``checker`` (3-D checkerboard of cell ``period``),
            ``stripes`` (bands along local x of width ``period / 2``), ``rings`` (concentric bands
            about the local z axis).
        a, b: the two RGB albedos in [0, 1].
        period: texture period in world units.
    """

    texture: Texture = "solid"
    a: tuple[float, float, float] = (0.8, 0.8, 0.8)
    b: tuple[float, float, float] = (0.2, 0.2, 0.2)
    period: float = 0.5


@dataclasses.dataclass(frozen=True)
class Sphere:
    """Sphere of ``radius`` about ``centre``; texture coordinates are world offsets from the centre."""

    centre: tuple[float, float, float]
    radius: float
    material: Material


@dataclasses.dataclass(frozen=True)
class Box:
    """Box with half-extents ``half`` about ``centre``, rotated by ``yaw`` radians about world z."""

    centre: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float
    material: Material


@dataclasses.dataclass(frozen=True)
class Plane:
    """Rectangle through ``centre`` with unit ``normal``, half-sizes ``half`` along its tangent axes.

    The tangent axes are ``u = normalize(up × normal)`` (``up`` = world z, or world x when the normal
    is parallel to z) and ``v = normal × u``. Both faces are visible.
    """

    centre: tuple[float, float, float]
    normal: tuple[float, float, float]
    half: tuple[float, float]
    material: Material


Primitive = Sphere | Box | Plane


@dataclasses.dataclass(frozen=True)
class Light:
    """Directional light: unit ``direction`` towards the light, diffuse ``intensity``, ``ambient``."""

    direction: tuple[float, float, float] = (0.4, -0.3, 0.87)
    intensity: float = 0.85
    ambient: float = 0.3


@dataclasses.dataclass
class Hit:
    """Nearest hits of ``R`` rays: ``t [R]`` (inf on a miss), ``normal [R,3]`` (unit, facing the
    ray), ``local [R,3]`` (texture coordinates), ``prim [R]`` (primitive index, -1 on a miss)."""

    t: torch.Tensor
    normal: torch.Tensor
    local: torch.Tensor
    prim: torch.Tensor


def _vec(x: tuple[float, ...]) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def _intersect_sphere(o: torch.Tensor, d: torch.Tensor, s: Sphere) -> tuple[torch.Tensor, ...]:
    c = _vec(s.centre)
    oc = o - c
    b = (oc * d).sum(-1)
    cc = (oc * oc).sum(-1) - s.radius**2
    disc = b * b - cc
    sq = disc.clamp_min(0).sqrt()
    t0, t1 = -b - sq, -b + sq
    t = torch.where(t0 > 1e-9, t0, t1)
    t = torch.where((disc >= 0) & (t > 1e-9), t, torch.full_like(t, _INF))
    p = o + d * torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None]
    return t, (p - c) / s.radius, p - c


def _rot_z(yaw: float) -> torch.Tensor:
    c, s = math.cos(yaw), math.sin(yaw)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _intersect_box(o: torch.Tensor, d: torch.Tensor, bx: Box) -> tuple[torch.Tensor, ...]:
    R = _rot_z(bx.yaw)  # local → world
    c, h = _vec(bx.centre), _vec(bx.half)
    ol = (o - c) @ R
    dl = d @ R
    safe = torch.where(dl.abs() < 1e-12, torch.full_like(dl, 1e-12), dl)
    ta, tb = (-h - ol) / safe, (h - ol) / safe
    tmin, tmax = torch.minimum(ta, tb), torch.maximum(ta, tb)
    t_near, axis_near = tmin.max(-1)
    t_far, axis_far = tmax.min(-1)
    inside = t_near <= 1e-9
    t = torch.where(inside, t_far, t_near)
    axis = torch.where(inside, axis_far, axis_near)
    t = torch.where((t_near <= t_far) & (t > 1e-9), t, torch.full_like(t, _INF))
    pl = ol + dl * torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None]
    nl = torch.zeros_like(pl)
    nl.scatter_(1, axis[:, None], torch.sign(torch.gather(pl, 1, axis[:, None])))
    return t, nl @ R.T, pl


def _plane_axes(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    up = _vec((0.0, 0.0, 1.0)) if abs(float(normal[2])) < 0.99 else _vec((1.0, 0.0, 0.0))
    u = torch.linalg.cross(up, normal)
    u = u / u.norm()
    return u, torch.linalg.cross(normal, u)


def _intersect_plane(o: torch.Tensor, d: torch.Tensor, pl: Plane) -> tuple[torch.Tensor, ...]:
    n = _vec(pl.normal)
    n = n / n.norm()
    c = _vec(pl.centre)
    u, v = _plane_axes(n)
    dn = d @ n
    safe = torch.where(dn.abs() < 1e-12, torch.full_like(dn, 1e-12), dn)
    t = ((c - o) @ n) / safe
    p = o + d * t[:, None]
    lu, lv = (p - c) @ u, (p - c) @ v
    ok = (t > 1e-9) & (lu.abs() <= pl.half[0]) & (lv.abs() <= pl.half[1]) & (dn.abs() >= 1e-12)
    t = torch.where(ok, t, torch.full_like(t, _INF))
    return t, n.expand_as(p), torch.stack([lu, lv, torch.zeros_like(lu)], -1)


def intersect(origins: torch.Tensor, dirs: torch.Tensor, prims: list[Primitive]) -> Hit:
    """Nearest intersection of rays ``origins [R,3]``, unit ``dirs [R,3]`` with ``prims``."""
    R = origins.shape[0]
    best = Hit(t=torch.full((R,), _INF, dtype=torch.float64), normal=torch.zeros(R, 3, dtype=torch.float64),
               local=torch.zeros(R, 3, dtype=torch.float64), prim=torch.full((R,), -1, dtype=torch.long))
    for i, prim in enumerate(prims):
        if isinstance(prim, Sphere):
            t, n, loc = _intersect_sphere(origins, dirs, prim)
        elif isinstance(prim, Box):
            t, n, loc = _intersect_box(origins, dirs, prim)
        elif isinstance(prim, Plane):
            t, n, loc = _intersect_plane(origins, dirs, prim)
        else:
            raise TypeError(f"prims[{i}]: expected Sphere, Box or Plane, got {type(prim).__name__}")
        closer = t < best.t
        best.t = torch.where(closer, t, best.t)
        best.normal = torch.where(closer[:, None], n, best.normal)
        best.local = torch.where(closer[:, None], loc, best.local)
        best.prim = torch.where(closer, torch.full_like(best.prim, i), best.prim)
    # Shade the face the ray sees (planes are two-sided).
    facing = (best.normal * dirs).sum(-1, keepdim=True) > 0
    best.normal = torch.where(facing, -best.normal, best.normal)
    return best


def albedo(material: Material, local: torch.Tensor) -> torch.Tensor:
    """RGB albedo ``[R,3]`` of ``material`` at texture coordinates ``local [R,3]``."""
    a, b = _vec(material.a), _vec(material.b)
    p = material.period
    if material.texture == "solid":
        w = torch.zeros(local.shape[0], dtype=torch.float64)
    elif material.texture == "checker":
        cells = torch.floor(local / p + 1e-7).sum(-1)
        w = torch.remainder(cells, 2.0)
    elif material.texture == "stripes":
        w = (torch.remainder(local[:, 0] / p, 1.0) >= 0.5).double()
    elif material.texture == "rings":
        r = local[:, :2].norm(dim=-1)
        w = (torch.remainder(r / p, 1.0) >= 0.5).double()
    else:
        raise ValueError(f"material.texture: expected one of {Texture.__args__}, got {material.texture!r}")
    return a + (b - a) * w[:, None]


def camera_rays(viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                supersample: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays of one camera: ``(origins [H*W*s², 3], dirs [H*W*s², 3])``.

    Rays are ordered pixel-major (row, column, then the ``s×s`` sub-pixel grid), so a reshape to
    ``[H, W, s*s, ...]`` groups each pixel's sub-samples. Sub-sample offsets are the centres of an
    ``s×s`` grid inside the pixel (``s = 1`` gives the pixel centre).
    """
    s = supersample
    sub = (torch.arange(s, dtype=torch.float64) + 0.5) / s
    rows = torch.arange(height, dtype=torch.float64)[:, None, None, None] + sub[None, None, :, None]
    cols = torch.arange(width, dtype=torch.float64)[None, :, None, None] + sub[None, None, None, :]
    v = rows.expand(height, width, s, s).reshape(-1)
    u = cols.expand(height, width, s, s).reshape(-1)
    pix = torch.stack([u, v, torch.ones_like(u)], -1)
    cam = torch.linalg.solve(K.double(), pix.T).T
    V = viewmat.double()
    Rm, t = V[:3, :3], V[:3, 3]
    dirs = torch.nn.functional.normalize(cam @ Rm, dim=-1)  # Rᵀ applied to row vectors
    origin = -(Rm.T @ t)
    return origin.expand_as(dirs).contiguous(), dirs


def render(prims: list[Primitive], light: Light, viewmat: torch.Tensor, K: torch.Tensor, width: int,
           height: int, supersample: int = 2, shadows: bool = True) -> torch.Tensor:
    """Ray-trace one view: straight (not premultiplied) RGBA ``[H, W, 4]`` float64 in [0, 1].

    Alpha is the pixel's coverage (fraction of its ``supersample²`` rays that hit something); the
    colour is the average over the rays that hit (0 where nothing is hit).
    """
    origins, dirs = camera_rays(viewmat, K, width, height, supersample)
    rgb, found = shade(prims, light, origins, dirs, shadows)
    n_sub = supersample * supersample
    cover = found.double().reshape(height, width, n_sub)
    colour_sum = rgb.reshape(height, width, n_sub, 3).sum(2)
    alpha = cover.mean(-1, keepdim=True)
    colour = colour_sum / cover.sum(-1, keepdim=True).clamp_min(1.0)
    return torch.cat([colour, alpha], -1)


def shade(prims: list[Primitive], light: Light, origins: torch.Tensor, dirs: torch.Tensor,
          shadows: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Shaded colour of rays ``origins [R,3]``, unit ``dirs [R,3]`` (float64): ``(rgb [R,3] in [0, 1],
    found [R] bool)``; rays that hit nothing are black with ``found`` false."""
    hit = intersect(origins, dirs, prims)
    found = hit.prim >= 0
    pts = origins + dirs * torch.where(found, hit.t, torch.zeros_like(hit.t))[:, None]
    L = _vec(light.direction)
    L = L / L.norm()
    lambert = (hit.normal @ L).clamp_min(0.0)
    if shadows:
        shadow = intersect(pts + 1e-6 * hit.normal, L.expand_as(pts).contiguous(), prims)
        lambert = torch.where(shadow.prim >= 0, torch.zeros_like(lambert), lambert)
    rgb = torch.zeros_like(pts)
    for i, prim in enumerate(prims):
        sel = hit.prim == i
        if bool(sel.any()):
            rgb[sel] = albedo(prim.material, hit.local[sel])
    rgb = rgb * (light.ambient + light.intensity * lambert)[:, None]
    return torch.where(found[:, None], rgb.clamp(0.0, 1.0), torch.zeros_like(rgb)), found
