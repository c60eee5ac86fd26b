"""Fitting an export's Gaussians to nsplat's own renders (distillation): what ``export --format 3dgs`` does after
the kernel conversion, so that a 3DGS rasteriser shows what nsplat shows.

The classic conversion (:mod:`nsplat.gaussians.kernel`) writes one opacity per Gaussian where nsplat's kernel has
a view-dependent peak; a fit can spread that error better than a mean. Starting from the converted Gaussians,
Adam minimises the mean squared error between the differentiable 3DGS rasteriser's image
(:func:`nsplat.gaussians.raster.rasterize`) and nsplat's render of every training camera (the op with the run's
evaluation settings, the mean of ``draws`` draws; no ground truth is used). It fits the opacities (logits), the
two tangent std-devs (logs; the flat axis stays :data:`~nsplat.gaussians.ply.FLAT` of the larger), the colour as
degree-``sh_degree`` spherical harmonics (a 3DGS file holds degree 3 whatever the model had) and, with
``lr_means > 0``, the positions; rotations (normals) stay.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import time

import torch

from nsplat.gaussians.ply import FLAT
from nsplat.gaussians.raster import rasterize
from nsplat.ops.projection import tangent_frame
from nsplat.render.renderer import DRAW_STRIDE, render
from nsplat.render.sh import view_channels, view_colour
from nsplat.render.view_model import ViewModel

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """Settings of :func:`fit_gaussians` (learning rates are Adam's, per step of one camera).

    Attributes:
        epochs: passes over the training cameras (0: no fit). draws: op draws averaged per target image.
        lr_opacity: on opacity logits. lr_scale: on log std-devs. lr_colour: on the colour (band 0, in [0, 1]
            units); the higher bands learn at ``lr_colour · sh_rest_factor``. lr_means: on positions, in units
            of the scene's extent (0: positions stay). sh_degree: degree of the fitted colour (0 … 3).
        seed: the camera order's RNG seed.
    """

    epochs: int = 3
    draws: int = 2
    lr_opacity: float = 0.05
    lr_scale: float = 0.01
    lr_colour: float = 0.005
    sh_rest_factor: float = 0.25
    lr_means: float = 0.0005
    sh_degree: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("epochs", "draws", "lr_opacity", "lr_scale", "lr_colour", "sh_rest_factor", "lr_means"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")
        if self.draws < 1:
            raise ValueError(f"draws: expected an int >= 1, got {self.draws!r}")
        if self.sh_degree not in (0, 1, 2, 3):
            raise ValueError(f"sh_degree: expected 0, 1, 2 or 3, got {self.sh_degree!r}")


@dataclasses.dataclass
class Gaussians:
    """Flat Gaussians as :func:`nsplat.gaussians.ply.write_gaussian_ply` writes them: ``means [N,3]``, unit
    ``normals [N,3]``, tangent std-devs ``scales [N,2]``, ``opacities [N]`` in [0, 1] and colour ``features
    [N, 3·(L+1)²]`` (this project's SH convention, :mod:`nsplat.render.sh`)."""

    means: torch.Tensor
    normals: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    features: torch.Tensor


def covariances(normals: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariances ``[N,3,3]`` of flat Gaussians with unit ``normals [N,3]`` and std-devs ``scales [N,2]``
    along the op's tangent frame, the normal axis at :data:`FLAT` of the larger (as the file stores them)."""
    t0, t1 = tangent_frame(normals)
    flat = FLAT * scales.max(1).values
    axes = torch.stack([t0, t1, normals], -1)                               # columns
    var = torch.stack([scales[:, 0] ** 2, scales[:, 1] ** 2, flat ** 2], -1)
    return (axes * var[:, None, :]) @ axes.transpose(1, 2)


@torch.no_grad()
def nsplat_targets(model: ViewModel, draws: int) -> torch.Tensor:
    """nsplat's renders ``[V,H,W,3]`` of ``model``'s training cameras (its ``render_cfg``, op seed ``model.seed
    + v`` for camera ``v``, the mean of ``draws`` draws; its shading, or its SH colour seen from each camera)."""
    cams = model.cameras
    out = []
    for v in range(cams.viewmats.shape[0]):
        V, K = cams.viewmats[v:v + 1].to(model.means), cams.Ks[v:v + 1].to(model.means)
        feats = model.features.detach()
        if model.colours is not None:
            feats = model.colours(feats, model.normals.detach(), V)
            feats = feats[0] if feats.dim() == 3 else feats
        elif model.sh_degree is not None:
            feats = view_colour(feats, model.means.detach(), V[0])
        imgs = [render(model.means.detach(), model.normals.detach(), model.scales.detach(),
                       model.opacities.detach(), feats, V, K, cams.width, cams.height, model.render_cfg,
                       seed=model.seed + v + j * DRAW_STRIDE, background=model.background).image[0, ..., :3]
                for j in range(draws)]
        out.append(torch.stack(imgs).mean(0).clamp(0, 1))
    return torch.stack(out)


def _padded(features: torch.Tensor, degree: int) -> torch.Tensor:
    """``features [N, 3·(L+1)²]`` with bands above ``degree`` dropped and missing ones zero."""
    out = features.new_zeros(features.shape[0], view_channels(degree))
    n = min(out.shape[1], features.shape[1])
    out[:, :n] = features[:, :n]
    return out


def fit_gaussians(start: Gaussians, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                  targets: torch.Tensor, background: torch.Tensor, settings: FitSettings, *,
                  antialiased: bool = False) -> tuple[Gaussians, dict]:
    """Fit Gaussians to target images (module docstring).

    Args:
        start: the converted Gaussians. viewmats ``[V,4,4]``, Ks ``[V,3,3]``: the cameras of ``targets
        [V,H,W,3]`` (``width × height``). background ``[3]``. antialiased: fit for Mip-Splatting's compensation.

    Returns:
        ``(fitted, history)``: float32 Gaussians (normals as given) and ``{"mse": [per-epoch mean], "seconds": t}``.
    """
    with torch.enable_grad():                                               # also when called under no_grad
        return _fit(start, viewmats, Ks, width, height, targets, background, settings, antialiased)


def _fit(start: Gaussians, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, targets: torch.Tensor,
         background: torch.Tensor, settings: FitSettings, antialiased: bool) -> tuple[Gaussians, dict]:
    """:func:`fit_gaussians`' loop (the same arguments), with gradients on."""
    dt = torch.float32
    means0 = start.means.detach().to(dt)
    extent = float((means0.max(0).values - means0.min(0).values).norm())
    normals = torch.nn.functional.normalize(start.normals.detach().to(dt), dim=-1)
    params = {"means": means0.clone().requires_grad_(settings.lr_means > 0),
              "log_scales": start.scales.detach().to(dt).log().requires_grad_(),
              "logits": torch.logit(start.opacities.detach().to(dt).clamp(1e-4, 1 - 1e-4)).requires_grad_(),
              "dc": start.features.detach().to(dt)[:, :3].clone().requires_grad_(),
              "rest": _padded(start.features.detach().to(dt), settings.sh_degree)[:, 3:].clone().requires_grad_()}
    groups = [{"params": [params["log_scales"]], "lr": settings.lr_scale},
              {"params": [params["logits"]], "lr": settings.lr_opacity},
              {"params": [params["dc"]], "lr": settings.lr_colour},
              {"params": [params["rest"]], "lr": settings.lr_colour * settings.sh_rest_factor}]
    if settings.lr_means > 0:
        groups.append({"params": [params["means"]], "lr": settings.lr_means * extent})
    opt = torch.optim.Adam(groups, eps=1e-15)
    gen = torch.Generator().manual_seed(settings.seed)
    history: dict = {"mse": []}
    t0 = time.perf_counter()
    bg = background.detach().to(dt)
    for epoch in range(settings.epochs):
        total = 0.0
        for v in torch.randperm(viewmats.shape[0], generator=gen).tolist():
            feats = torch.cat([params["dc"], params["rest"]], 1)
            colours = view_colour(feats, params["means"], viewmats[v].to(dt))
            cov = covariances(normals, params["log_scales"].exp())
            img = rasterize(params["means"], cov, torch.sigmoid(params["logits"]), colours, viewmats[v].to(dt),
                            Ks[v].to(dt), width, height, bg, antialiased=antialiased)
            loss = torch.mean((img - targets[v].to(dt)) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach())
        history["mse"].append(total / viewmats.shape[0])
        log.info("3dgs fit: epoch %d/%d, mse %.3g (%.0f s)", epoch + 1, settings.epochs, history["mse"][-1],
                 time.perf_counter() - t0)
    history["seconds"] = time.perf_counter() - t0
    with torch.no_grad():
        fitted = Gaussians(params["means"].detach().clone(), normals, params["log_scales"].exp(),
                           torch.sigmoid(params["logits"]), torch.cat([params["dc"], params["rest"]], 1))
    return fitted, history
