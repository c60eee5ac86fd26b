"""The embedded procedural scene: a few textured, shaded objects written in NeRF-synthetic format.

:func:`make_scene` draws a scene from a seed (an upright textured panel plus spheres and boxes with
procedural textures, one directional light); :func:`generate` ray-traces it with the analytic
ray tracer of :mod:`nsplat.data.raytrace` (not with the splatting op) from cameras on the upper
hemisphere and writes ``transforms_{train,val,test}.json`` plus RGBA PNGs, exactly the layout of
the NeRF-synthetic scenes; :func:`ensure_scene` does so once into a cache folder keyed by the
parameters. World axes follow Blender: z is up.
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
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from nsplat.cameras import intrinsics_from_fov, look_at
from nsplat.data.raytrace import Box, Light, Material, Plane, Primitive, Sphere, render

log = logging.getLogger(__name__)

#: Bumped whenever the generator's output changes, so stale caches are not reused.
GENERATOR_VERSION = 1
SPLITS = ("train", "val", "test")
_GL_FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


@dataclasses.dataclass(frozen=True)
class ProceduralSpec:
    """What to generate.

    Attributes:
        seed: scene and camera seed (same seed → byte-identical files).
        resolution: image width = height in pixels.
        views: number of views per split ``(train, val, test)``.
        objects: number of objects (the first is an upright panel).
        radius: camera distance from the origin.
        elevation: camera elevation range in degrees ``(min, max)`` above the horizontal.
        camera_angle_x: horizontal field of view in radians.
        supersample: rays per pixel side (anti-aliasing and fractional alpha at edges).
    """

    seed: int = 0
    resolution: int = 64
    views: tuple[int, int, int] = (40, 8, 8)
    objects: int = 4
    radius: float = 3.2
    elevation: tuple[float, float] = (10.0, 70.0)
    camera_angle_x: float = 0.6911112070083618
    supersample: int = 3

    def __post_init__(self) -> None:
        if self.resolution < 8:
            raise ValueError(f"resolution: expected >= 8 pixels, got {self.resolution}")
        if len(self.views) != 3 or min(self.views) < 1:
            raise ValueError(f"views: expected three positive counts (train, val, test), got {self.views}")
        if not 1 <= self.objects <= 8:
            raise ValueError(f"objects: expected 1..8, got {self.objects}")
        if not 0.0 <= self.elevation[0] <= self.elevation[1] < 90.0:
            raise ValueError(f"elevation: expected 0 <= min <= max < 90 degrees, got {self.elevation}")
        if self.supersample < 1:
            raise ValueError(f"supersample: expected >= 1, got {self.supersample}")

    def key(self) -> str:
        """Short hash of the spec and generator version (the cache folder's suffix)."""
        blob = json.dumps([GENERATOR_VERSION, dataclasses.asdict(self)], sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]


def _colour(rng: np.random.Generator) -> tuple[float, float, float]:
    hue = rng.uniform(0, 1)
    sat, val = rng.uniform(0.45, 0.85), rng.uniform(0.55, 0.95)
    k = (np.array([5.0, 3.0, 1.0]) + hue * 6.0) % 6.0
    rgb = val - val * sat * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return tuple(float(c) for c in rgb)


def make_scene(seed: int, objects: int = 4) -> tuple[list[Primitive], Light]:
    """Draw a scene from ``seed``: ``objects`` spheres, boxes and upright panels resting on ``z = 0``
    (no ground: like the NeRF-synthetic objects, the background stays transparent), plus the light.

    The first object is always an upright, two-sided textured panel (a :class:`Plane`).
    """
    rng = np.random.default_rng(seed)
    prims: list[Primitive] = []
    placed: list[tuple[float, float, float]] = []
    textures = ("checker", "stripes", "rings", "solid")
    attempts = 0
    while len(prims) < objects:
        attempts += 1
        if attempts > 10_000:
            raise RuntimeError(f"objects: could not place {objects} non-overlapping objects")
        shrink = 1.0 / (1.0 + attempts / 200.0)  # crowded scenes get smaller objects, never a hang
        size = float(rng.uniform(0.25, 0.45)) * shrink
        ang, dist = rng.uniform(0, 2 * math.pi), rng.uniform(0.0, 0.7)
        x, y = dist * math.cos(ang), dist * math.sin(ang)
        if any(math.hypot(x - px, y - py) < size + ps + 0.05 for px, py, ps in placed):
            continue
        placed.append((x, y, size))
        a = _colour(rng)
        b = tuple(0.15 + 0.7 * (1.0 - c) for c in a)  # a contrasting second tone
        mat = Material(textures[int(rng.integers(len(textures)))], a, b,
                       period=float(rng.uniform(0.2, 0.35)))
        kind = "plane" if not prims else ("sphere" if rng.uniform() < 0.5 else "box")
        if kind == "plane":
            yaw = float(rng.uniform(0, math.pi))
            prims.append(Plane(centre=(x, y, 1.1 * size), normal=(math.cos(yaw), math.sin(yaw), 0.0),
                               half=(size, 1.1 * size), material=dataclasses.replace(mat, texture="checker")))
        elif kind == "sphere":
            prims.append(Sphere(centre=(x, y, size), radius=size, material=mat))
        else:
            half = (size * 0.75, size * 0.75, float(rng.uniform(0.5, 1.2)) * size)
            prims.append(Box(centre=(x, y, half[2]), half=half, yaw=float(rng.uniform(0, math.pi)),
                             material=mat))
    az = rng.uniform(0, 2 * math.pi)
    el = rng.uniform(math.radians(40), math.radians(70))
    light = Light(direction=(math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
    return prims, light


def camera_poses(count: int, radius: float, elevation: tuple[float, float], rng: np.random.Generator,
                 target: tuple[float, float, float] = (0.0, 0.0, 0.3)) -> torch.Tensor:
    """``[count,4,4]`` OpenCV world→camera matrices on the upper hemisphere, looking at ``target``.

    Azimuths are stratified over the full circle (with jitter); elevations uniform in the range.
    """
    az = (np.arange(count) + rng.uniform(0, 1, count)) / count * 2 * math.pi
    el = np.radians(rng.uniform(elevation[0], elevation[1], count))
    eye = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1) * radius
    eye_t = torch.tensor(eye, dtype=torch.float64) + torch.tensor(target, dtype=torch.float64)
    tgt = torch.tensor(target, dtype=torch.float64).expand(count, 3)
    return look_at(eye_t, tgt, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def viewmat_to_opengl_c2w(viewmat: torch.Tensor) -> torch.Tensor:
    """OpenCV world→camera ``[...,4,4]`` → NeRF/Blender camera→world (OpenGL axes) ``[...,4,4]``.

    Inverse of :func:`nsplat.cameras.opengl_c2w_to_viewmat`.
    """
    return torch.linalg.inv(viewmat.double()) @ _GL_FLIP


def generate(spec: ProceduralSpec, out_dir: Path) -> Path:
    """Ray-trace ``spec`` and write a NeRF-synthetic scene folder at ``out_dir`` (created)."""
    out_dir = Path(out_dir)
    prims, light = make_scene(spec.seed, spec.objects)
    rng = np.random.default_rng([spec.seed, 1])
    W = H = spec.resolution
    K = intrinsics_from_fov(spec.camera_angle_x, W, H, dtype=torch.float64)[0]
    for split, count in zip(SPLITS, spec.views):
        (out_dir / split).mkdir(parents=True, exist_ok=True)
        views = camera_poses(count, spec.radius, spec.elevation, rng)
        frames = []
        for i in range(count):
            rgba = render(prims, light, views[i], K, W, H, supersample=spec.supersample)
            png = (rgba.numpy() * 255.0 + 0.5).clip(0, 255).astype(np.uint8)
            iio.imwrite(out_dir / split / f"r_{i}.png", png)
            frames.append({"file_path": f"./{split}/r_{i}",
                           "transform_matrix": viewmat_to_opengl_c2w(views[i]).tolist()})
        doc = {"camera_angle_x": spec.camera_angle_x, "frames": frames}
        (out_dir / f"transforms_{split}.json").write_text(json.dumps(doc, indent=1))
    (out_dir / "scene.json").write_text(json.dumps(
        {"generator_version": GENERATOR_VERSION, "spec": dataclasses.asdict(spec),
         "primitives": [dict(type=type(p).__name__, **dataclasses.asdict(p)) for p in prims],
         "light": dataclasses.asdict(light)}, indent=1))
    return out_dir


def ensure_scene(spec: ProceduralSpec, cache_dir: Path) -> Path:
    """Folder of the scene for ``spec`` under ``cache_dir``, generated on first use.

    Generation writes to a temporary sibling folder that is renamed into place, so concurrent
    callers and interrupted runs never see a half-written scene.
    """
    cache_dir = Path(cache_dir)
    target = cache_dir / f"procedural-s{spec.seed}-r{spec.resolution}-{spec.key()}"
    if (target / "transforms_test.json").is_file():
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    log.info("generating procedural scene (seed %d, %d px) into %s", spec.seed, spec.resolution, target)
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=cache_dir))
    try:
        generate(spec, tmp)
        os.chmod(tmp, 0o755)  # mkdtemp makes it private
        try:
            os.replace(tmp, target)
        except OSError:
            if not (target / "transforms_test.json").is_file():  # lost a race to a complete copy?
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target
