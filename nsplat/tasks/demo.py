"""Task "demo": render the embedded procedural surfel scene with the sampled op and write PNGs.

It exercises the whole op (projection, tree, sampling, compositing) from a config and is the smoke
test of a fresh install: ``python train.py --config configs/demo.yaml``.
"""
from __future__ import annotations

import dataclasses
import math

import imageio.v3 as iio
import numpy as np
import torch

from nsplat.cameras import intrinsics_from_fov, look_at
from nsplat.config import require, require_fields
from nsplat.ops.validation import memory_limit
from nsplat.render import renderer as gateway
from nsplat.render.renderer import RenderConfig, background_of
from nsplat.render.view_model import TrainingCameras, ViewModel
from nsplat.run.context import RunContext
from nsplat.run.report import results


@dataclasses.dataclass
class Config:
    """Demo settings.

    Attributes:
        task: ``demo``. seed: the scene's and the op's seed.
        points: surfels of the procedural scene. resolution: image side (px). views: cameras on the orbit.
        render: the render settings (:class:`nsplat.render.renderer.RenderConfig`; the shipped config: the sampled op on
            a white background).
        compare_dense: also render with the dense oracle and log the mean difference.
    """

    task: str = "demo"
    seed: int = 0
    points: int = 20000
    resolution: int = 128
    views: int = 4
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    compare_dense: bool = False

    def __post_init__(self) -> None:
        require_fields(self, seed=">=0", points=">=1", resolution=">=1", views=">=1")
        need = self.points * 256 + self.views * (512 + self.resolution**2 * (self.render.samples * 12 + 64))
        limit = memory_limit(torch.device("cpu"))
        require(need <= limit, "points/views/resolution/render.samples",
                f"a scene and images that fit in memory (about {need / 2**30:.3g} GiB needed, {limit / 2**30:.3g} GiB "
                f"available)", [self.points, self.views, self.resolution, self.render.samples])


def demo_scene(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A checker-textured sphere of surfels on a striped ground disc: ``n`` points, RGB features."""
    g = torch.Generator().manual_seed(seed)
    n_sphere = n * 2 // 3
    d = torch.nn.functional.normalize(torch.randn(n_sphere, 3, generator=g), dim=-1)
    sphere = 0.6 * d + torch.tensor([0.0, 0.0, 0.6])
    lon, lat = torch.atan2(d[:, 1], d[:, 0]), torch.asin(d[:, 2].clamp(-1, 1))
    checker = ((torch.floor(lon * 4 / math.pi) + torch.floor(lat * 4 / math.pi)) % 2)[:, None]
    col_s = checker * torch.tensor([0.9, 0.3, 0.2]) + (1 - checker) * torch.tensor([0.95, 0.9, 0.8])
    n_disc = n - n_sphere
    r = 1.6 * torch.sqrt(torch.rand(n_disc, generator=g))
    a = 2 * math.pi * torch.rand(n_disc, generator=g)
    disc = torch.stack([r * torch.cos(a), r * torch.sin(a), torch.zeros_like(r)], -1)
    stripe = ((torch.floor(r * 5)) % 2)[:, None]
    col_d = stripe * torch.tensor([0.2, 0.4, 0.8]) + (1 - stripe) * torch.tensor([0.8, 0.85, 0.9])
    normals = torch.cat([d, torch.tensor([0.0, 0.0, 1.0]).expand(n_disc, 3)])
    spacing = torch.cat([torch.full((n_sphere,), math.sqrt(4 * math.pi * 0.36 / max(n_sphere, 1))),
                         torch.full((n_disc,), math.sqrt(math.pi * 2.56 / max(n_disc, 1)))])
    return dict(means=torch.cat([sphere, disc]), normals=normals, scales=(0.6 * spacing)[:, None].repeat(1, 2),
                opacities=torch.full((n,), 0.9), features=torch.cat([col_s, col_d]))


def orbit_cameras(views: int, resolution: int, radius: float = 3.2) -> tuple[torch.Tensor, torch.Tensor]:
    """``views`` cameras on a circle at 30° elevation looking at the scene centre."""
    ang = torch.arange(views, dtype=torch.float32) * 2 * math.pi / views
    eye = torch.stack([radius * torch.cos(ang), radius * torch.sin(ang), torch.full_like(ang, radius * 0.55)], -1)
    target = torch.tensor([0.0, 0.0, 0.4]).expand_as(eye)
    V = look_at(eye, target, torch.tensor([0.0, 0.0, 1.0]))
    K = intrinsics_from_fov(math.radians(45.0), resolution, resolution, batch=views)
    return V, K


def run(cfg: Config, ctx: RunContext) -> None:
    """Render ``cfg.views`` views and write ``demo.png`` (a row of views) into the run folder."""
    torch.manual_seed(cfg.seed)
    sc = {k: v.to(ctx.device) for k, v in demo_scene(cfg.points, cfg.seed).items()}
    V, K = (t.to(ctx.device) for t in orbit_cameras(cfg.views, cfg.resolution))
    rcfg = cfg.render
    args = (sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, cfg.resolution,
            cfg.resolution)
    out = gateway.render(*args, rcfg, seed=ctx.seed)
    row = torch.cat(list(out.image.clamp(0, 1)), dim=1).cpu().numpy()
    path = ctx.run_dir / "demo.png"
    iio.imwrite(path, (row * 255).round().astype(np.uint8))
    results.info("wrote %s (%d views, %d points, samples=%d, mean kernel evaluations/pixel %.1f)", path, cfg.views,
             cfg.points, rcfg.samples, float(out.work.float().mean()))
    if cfg.compare_dense:
        ref = gateway.render(*args, dataclasses.replace(rcfg, renderer="dense"))
        err = float((out.image - ref.image).abs().mean())
        results.info("mean abs difference to the dense renderer: %.5f", err)


def view(cfg: Config, ctx: RunContext) -> ViewModel:
    """The task contract's ``view``: the demo scene with its orbit cameras and render settings."""
    sc = {k: v.to(ctx.device) for k, v in demo_scene(cfg.points, cfg.seed).items()}
    V, K = orbit_cameras(cfg.views, cfg.resolution)
    cams = TrainingCameras(V.to(ctx.device), K.to(ctx.device), cfg.resolution, cfg.resolution)
    bg = background_of(cfg.render, 3, sc["means"])
    return ViewModel(sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"],
                     torch.zeros(3, device=ctx.device) if bg is None else bg, render_cfg=cfg.render, cameras=cams,
                     task="demo", seed=cfg.seed)
