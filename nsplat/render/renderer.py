"""The render gateway: one :class:`RenderConfig` and one :func:`render` that every task, the demo, the
filters and the viewer go through (docs/architecture.md).

``RenderConfig.renderer`` picks the sampled op (``splat``, :func:`nsplat.ops.splat`, the target), the
dense oracle (``dense``, :func:`nsplat.ops.splat_dense`) or the truncated baseline (``truncated``,
:func:`nsplat.render.truncated.splat_truncated`). Every setting of the op lives here, once; the speed
knobs measured in docs/tradeoffs.md (``deterministic``, ``hermite_order``/``hermite_tol``) are one config
line each. :func:`render_views` adds per-camera Lambert shading of albedo scenes.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import torch

from nsplat.config import FieldError, require, require_fields
from nsplat.ops import SplatOutput, SplatSettings, splat, splat_dense
from nsplat.render.sh import view_colour
from nsplat.render.shading import lambert
from nsplat.render.truncated import splat_truncated
from nsplat.scene import SurfelScene

#: Seed offset between the independent draws of an averaged render (``draws`` > 1).
DRAW_STRIDE = 1 << 20

RENDERERS = ("splat", "dense", "truncated")


@dataclasses.dataclass
class RenderConfig:
    """Which renderer and with which settings (the op's arguments, see :func:`nsplat.ops.splat`).

    The op's fields (``samples`` … ``backface_cull``) are exactly those of :class:`nsplat.ops.SplatSettings`,
    with its defaults; :meth:`op_settings` builds the value the op and :class:`nsplat.ops.Splatter` take
    (and, for the sampled renderer, validates it with the op's own checks at construction).

    Attributes:
        renderer: ``splat`` (sampled op), ``dense`` (exact oracle) or ``truncated`` (3σ baseline).
        samples: samples per pixel m. eps: the sampler's error threshold ε.
        estimator: gradient estimator ``ht`` / ``ht-pips`` / ``paper`` / ``sampled`` (docs/method.md).
        stratified: stratified (rank-1 lattice) uniforms across pixels.
        backface_cull: cull surfels whose normal faces away from the camera (every renderer; default:
            two-sided surfels).
        composite: ``alpha`` (front-to-back) or ``additive``.
        background: colour composited under the splats (``null``: zeros; a per-call tensor overrides it).
        near, far: depth clipping range. lowpass: screen-space low-pass variance (px²).
        deterministic: fixed-order backward (``false``: atomics on CPU, faster and not bitwise reproducible;
            measured in docs/tradeoffs.md). hermite_order, hermite_tol: the sampler's Hermite expansions.
        cutoff: truncation radius in σ for ``truncated``.
    """

    renderer: Literal["splat", "dense", "truncated"] = "splat"
    samples: int = SplatSettings.samples
    eps: float = SplatSettings.eps
    estimator: Literal["ht", "ht-pips", "paper", "sampled"] = SplatSettings.estimator
    stratified: bool = SplatSettings.stratified
    backface_cull: bool = SplatSettings.backface_cull
    composite: Literal["alpha", "additive"] = SplatSettings.composite
    background: list[float] | None = None
    near: float = SplatSettings.near
    far: float = SplatSettings.far
    lowpass: float = SplatSettings.lowpass
    deterministic: bool = SplatSettings.deterministic
    hermite_order: int = SplatSettings.hermite_order
    hermite_tol: float = SplatSettings.hermite_tol
    cutoff: float = 3.0

    def __post_init__(self) -> None:
        require_fields(self, samples=">=1", eps="prob", near=">0", lowpass=">=0", cutoff=">0",
                       hermite_order=">=0", hermite_tol=">0")
        require(self.far > self.near, "far", f"a value > near ({self.near})", self.far)
        require(self.renderer != "truncated" or self.composite == "alpha", "composite",
                "alpha with renderer truncated", self.composite)
        if self.renderer == "splat":  # the op's own checks (e.g. hermite_order <= 16), at construction
            try:
                self.op_settings()
            except (TypeError, ValueError) as exc:  # "<name>: expected ..., got ...": a config field error
                key, _, rest = str(exc).partition(": ")
                expected = rest.removeprefix("expected ").rsplit(", got ", 1)[0]
                raise FieldError(key, expected, getattr(self, key, None)) from None

    def op_settings(self, estimator: str | None = None) -> SplatSettings:
        """The sampled op's settings of this config (``estimator`` overrides ``self.estimator``)."""
        settings = SplatSettings.of(self)
        return settings if estimator is None else dataclasses.replace(settings, estimator=estimator)


def background_of(cfg: RenderConfig, channels: int, like: torch.Tensor) -> torch.Tensor | None:
    """``cfg.background`` as a ``[channels]`` tensor like ``like`` (``None`` when unset).

    Raises:
        ValueError: the configured background has another number of channels.
    """
    if cfg.background is None:
        return None
    if len(cfg.background) != channels:
        raise ValueError(f"render.background: expected {channels} values for {channels}-channel features, "
                         f"got {list(cfg.background)}")
    bg = like.new_empty(channels)  # filled from Python scalars: torch.tensor(..., device=) would copy from the host
    for c, value in enumerate(cfg.background):
        bg[c].fill_(value)
    return bg


def render(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
           features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
           cfg: RenderConfig, *, seed: int | torch.Tensor = 0, background: torch.Tensor | None = None,
           estimator: str | None = None) -> SplatOutput:
    """Render ``[N]`` surfels into ``[B]`` cameras with the renderer ``cfg.renderer``.

    Args:
        means ``[N,3]``, normals ``[N,3]``, scales ``[N,2]``, opacities ``[N]``, features ``[N,C]`` (or ``[B,N,C]``,
        per camera, with the renderer ``splat`` or ``dense``).
        viewmats ``[B,4,4]`` (OpenCV world→camera), Ks ``[B,3,3]``; width, height in pixels.
        seed: the sampled op's RNG seed (see :func:`nsplat.run.engine.op_seed`), or a ``[B]`` int64 tensor of one
            seed per camera (op.md §3).
        background: ``[C]`` tensor overriding ``cfg.background`` (differentiable).
        estimator: overrides ``cfg.estimator``.

    Returns:
        :class:`~nsplat.ops.SplatOutput`: ``image [B,H,W,C]``, ``alpha``/``depth [B,H,W,1]``.
    """
    if background is None:
        background = background_of(cfg, features.shape[-1], means)
    common = dict(background=background, near=cfg.near, far=cfg.far, lowpass=cfg.lowpass,
                  backface_cull=cfg.backface_cull)
    if cfg.renderer == "splat":
        return splat(means, normals, scales, opacities, features, viewmats, Ks, width, height,
                     seed=seed if isinstance(seed, torch.Tensor) else int(seed),
                     background=background, **cfg.op_settings(estimator).kwargs())
    if cfg.renderer == "dense":
        return splat_dense(means, normals, scales, opacities, features, viewmats, Ks, width, height,
                           composite=cfg.composite, **common)
    if cfg.renderer == "truncated":
        return splat_truncated(means, normals, scales, opacities, features, viewmats, Ks, width, height,
                               cutoff=cfg.cutoff, **common)
    raise ValueError(f"render.renderer: expected one of {RENDERERS}, got {cfg.renderer!r}")


def render_views(scene: SurfelScene, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                 cfg: RenderConfig, *, seed: int | torch.Tensor = 0, shading: Literal["lambert", "none",
                                                                                      "sh"] = "lambert",
                 background: torch.Tensor | None = None, with_alpha: bool = False, with_means2d: bool = False,
                 draws: int = 1) -> torch.Tensor | tuple[torch.Tensor, ...]:
    """Images ``[B,H,W,C]`` of ``scene`` from cameras ``viewmats [B,4,4]``, ``Ks [B,3,3]`` (with
    ``with_alpha``: ``(images, alpha [B,H,W,1])``; with ``with_means2d`` the projected screen means of each op
    call follow, a list of ``[b,N,2]`` (the cameras in order) in the graph: their gradient is each camera's
    screen-space gradient, ``SplatOutput.means2d``).

    ``draws``: the images (and alpha) are the mean of that many independent op draws, draw ``j`` rendered
    with every seed shifted by ``j·DRAW_STRIDE`` (draw 0 is the one-draw render): less sampling noise in
    evaluation renders of the stochastic op, at ``draws`` times the cost.

    With ``shading="lambert"`` the scene features are albedo and are shaded per camera with the
    paper's camera-relative lights (:func:`nsplat.render.shading.lambert`); with ``shading="sh"`` they are
    view-dependent RGB (spherical harmonics, :func:`nsplat.render.sh.view_colour`) evaluated per camera. Either way the
    cameras' colours ``[B,N,3]`` are rendered in one op call (per-camera features) with the renderer ``splat``,
    camera ``b`` with op seed ``seed + b`` (as the only camera of a call with that seed; other renderers: one call
    per camera). With ``shading="none"`` the cameras are rendered in one op call. ``seed`` may be a ``[B]`` int64
    tensor of one seed per camera (camera ``b`` then samples as the only camera of a call with seed ``seed[b]``,
    op.md §3).
    """
    if draws < 1:
        raise ValueError(f"draws: expected an int >= 1, got {draws}")
    if isinstance(seed, torch.Tensor) and draws > 1:
        raise ValueError("seed: one seed per camera needs one draw")
    if with_means2d and draws > 1:
        raise ValueError("with_means2d: the screen means of one draw only (draws=1)")
    if draws > 1:
        runs = [render_views(scene, viewmats, Ks, width, height, cfg, seed=seed + j * DRAW_STRIDE, shading=shading,
                             background=background, with_alpha=True) for j in range(draws)]
        image = torch.stack([r[0] for r in runs]).mean(0)
        return (image, torch.stack([r[1] for r in runs]).mean(0)) if with_alpha else image
    if shading == "none":
        outs = [render(scene.means, scene.normals, scene.scales, scene.opacities, scene.features, viewmats, Ks,
                       width, height, cfg, seed=seed, background=background)]
    else:
        normals, means, B = scene.normals, scene.means, viewmats.shape[0]
        if shading == "sh":
            shaded = torch.stack([view_colour(scene.features, means, viewmats[b]) for b in range(B)])
        else:
            shaded = lambert(scene.features, normals, viewmats)
        seeds = seed if isinstance(seed, torch.Tensor) else torch.arange(B) + seed
        if cfg.renderer == "splat":
            outs = [render(means, normals, scene.scales, scene.opacities, shaded, viewmats, Ks, width, height, cfg,
                           seed=seeds, background=background)]
        else:
            outs = [render(means, normals, scene.scales, scene.opacities, shaded[b], viewmats[b:b + 1],
                           Ks[b:b + 1], width, height, cfg, seed=int(seeds[b]), background=background)
                    for b in range(B)]
    result = [torch.cat([o.image for o in outs], 0)]
    if with_alpha:
        result.append(torch.cat([o.alpha for o in outs], 0))
    if with_means2d:
        result.append([o.means2d for o in outs])
    return tuple(result) if len(result) > 1 else result[0]


@torch.no_grad()
def render_geometry(means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                    viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, cfg: RenderConfig, *,
                    seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(alpha [B,H,W,1], depth [B,H,W,1], normal [B,H,W,3])`` of surfels ``[N]`` from cameras ``viewmats [B,4,4]``:
    coverage, alpha-normalised camera depth (0 where empty) and the composited camera-space (OpenCV) normal,
    each surfel's turned to face the camera (surfels are two-sided), renormalised (0 where empty). One op call
    per camera (camera ``b`` with seed ``seed + b``), the camera-space normals splatted as features."""
    outs = []
    for b in range(viewmats.shape[0]):
        R, t = viewmats[b, :3, :3], viewmats[b, :3, 3]
        n_cam = torch.nn.functional.normalize(normals, dim=-1) @ R.T
        facing = torch.where(((means @ R.T + t) * n_cam).sum(-1, keepdim=True) > 0, -n_cam, n_cam)
        out = render(means, normals, scales, opacities, facing, viewmats[b:b + 1], Ks[b:b + 1], width, height, cfg,
                     seed=seed + b, background=torch.zeros(3, dtype=means.dtype, device=means.device))
        normal = torch.nn.functional.normalize(out.image, dim=-1) * (out.alpha > 0)
        outs.append((out.alpha, out.normalized_depth, normal))
    return tuple(torch.cat(parts) for parts in zip(*outs))
