"""How the viewer renders a :class:`~nsplat.render.view_model.ViewModel`: the pure render function.

:func:`render_view` maps one camera (OpenCV ``viewmat [4,4]`` world→camera, ``K [3,3]`` in pixels,
``width``, ``height``) and :class:`RenderSettings` to :class:`ViewImages` (RGB, feature preview,
alpha, depth). The web server, the live training view and the tests all call it, so "what the
browser shows" and "a direct render of that camera" are the same computation. The tasks build the
:class:`~nsplat.render.view_model.ViewModel` (:mod:`nsplat.render.view_model`); this module only renders it.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
import torch

from nsplat.render.renderer import RenderConfig, render
from nsplat.render.view_model import ViewModel
from nsplat.viewer.config import ViewerConfig

Mode = Literal["rgb", "features", "alpha", "depth"]
MODES: tuple[str, ...] = ("rgb", "features", "alpha", "depth")


@dataclasses.dataclass
class RenderSettings:
    """What the viewer's panel currently renders with (the speed/accuracy knobs); it starts from the run's
    ``render`` section with the ``viewer`` settings applied (:meth:`start`).

    Attributes:
        render: the render settings (samples per pixel m, ε, …; the viewer always renders with the sampled op).
        resolution: longest image side in pixels of a browser camera's render.
        mode: displayed image (``rgb``, ``features``, ``alpha``, ``depth``).
    """

    render: RenderConfig
    resolution: int
    mode: Mode = "rgb"

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode: expected one of {list(MODES)}, got {self.mode!r}")
        if self.resolution < 8:
            raise ValueError(f"resolution: expected >= 8 pixels, got {self.resolution}")

    @classmethod
    def start(cls, run: RenderConfig, viewer: ViewerConfig) -> "RenderSettings":
        """The panel's initial settings: the run's render settings ``run`` with ``viewer.render`` applied, at
        ``viewer.resolution``."""
        return cls(render=dataclasses.replace(viewer.render_cfg(run), renderer="splat"), resolution=viewer.resolution)

    def with_samples(self, samples: int, eps: float | None = None) -> "RenderSettings":
        """The same settings with ``samples`` per pixel (and ε ``eps``)."""
        render = dataclasses.replace(self.render, samples=samples, eps=self.render.eps if eps is None else eps)
        return dataclasses.replace(self, render=render)


@dataclasses.dataclass
class ViewImages:
    """One rendered camera: ``rgb [H,W,3]`` in [0, 1], ``features [H,W,C]`` (splatted, before any
    shader), ``alpha [H,W,1]`` and ``depth [H,W,1]`` (alpha-normalised camera z, 0 where empty)."""

    rgb: torch.Tensor
    features: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor


@torch.no_grad()
def render_view(model: ViewModel, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                settings: RenderSettings) -> ViewImages:
    """Render ``model`` from one camera through the render gateway (and the shader, if any).

    Args:
        viewmat: ``[4,4]`` OpenCV world→camera. K: ``[3,3]`` intrinsics in pixels.
        width, height: image size in pixels. settings: the render settings (``mode`` is ignored here).
    """
    dev, dt = model.means.device, model.means.dtype
    V = viewmat.to(dev, dt).reshape(1, 4, 4)
    Kb = K.to(dev, dt).reshape(1, 3, 3)
    normals = model.normals.detach()
    feats = model.features.detach()
    if model.colours is not None:
        feats = model.colours(feats, normals, V)
        feats = feats[0] if feats.dim() == 3 else feats
    cfg = settings.render
    out = render(model.means.detach(), normals, model.scales.detach(), model.opacities.detach(), feats, V, Kb,
                 int(width), int(height), cfg, seed=model.seed, background=model.background.to(dev, feats.dtype))
    image, alpha = out.image[0], out.alpha[0]
    if model.shader is not None:
        cond = torch.cat([image, alpha], -1) if model.alpha_input else image
        rgb = model.shader(cond.permute(2, 0, 1)[None].contiguous())[0].permute(1, 2, 0)
    else:
        rgb = image[..., :3] if image.shape[-1] >= 3 else image[..., :1].expand(-1, -1, 3)
    return ViewImages(rgb=rgb.clamp(0, 1), features=image, alpha=alpha, depth=out.normalized_depth[0])


_TURBO: np.ndarray | None = None


def _turbo() -> np.ndarray:
    global _TURBO
    if _TURBO is None:
        from matplotlib import colormaps

        _TURBO = (colormaps["turbo"](np.linspace(0, 1, 256))[:, :3] * 255 + 0.5).astype(np.uint8)
    return _TURBO


def to_display(images: ViewImages, mode: Mode) -> np.ndarray:
    """``[H,W,3]`` uint8 picture of ``images`` in ``mode``.

    ``features``: first three channels, min-max normalised over the covered pixels; ``alpha``: grey;
    ``depth``: turbo colour map between the 2nd and 98th percentile of the covered pixels (black: empty).
    """
    if mode == "rgb":
        x = images.rgb
    elif mode == "features":
        f = images.features
        f = f[..., :3] if f.shape[-1] >= 3 else f[..., :1].expand(-1, -1, 3)
        covered = images.alpha[..., 0] > 0.5
        ref = f[covered] if bool(covered.any()) else f.reshape(-1, 3)
        lo, hi = ref.min(0).values, ref.max(0).values
        x = ((f - lo) / (hi - lo).clamp_min(1e-8)).clamp(0, 1)
    elif mode == "alpha":
        x = images.alpha.clamp(0, 1).expand(-1, -1, 3)
    elif mode == "depth":
        d, covered = images.depth[..., 0], images.alpha[..., 0] > 0.5
        if not bool(covered.any()):
            return np.zeros((*d.shape, 3), np.uint8)
        vals = d[covered].float()
        lo, hi = torch.quantile(vals, 0.02), torch.quantile(vals, 0.98)
        t = ((d.float() - lo) / (hi - lo).clamp_min(1e-8)).clamp(0, 1)
        idx = (t * 255 + 0.5).long().cpu().numpy()
        pic = _turbo()[idx]
        pic[~covered.cpu().numpy()] = 0
        return pic
    else:
        raise ValueError(f"mode: expected one of {list(MODES)}, got {mode!r}")
    return (x.detach().float().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def render_display(model: ViewModel, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                   settings: RenderSettings) -> np.ndarray:
    """:func:`render_view` then :func:`to_display` in ``settings.mode``: ``[H,W,3]`` uint8."""
    return to_display(render_view(model, viewmat, K, width, height, settings), settings.mode)
