"""The op's settings as one value: :class:`SplatSettings`.

:class:`nsplat.ops.Splatter` holds one, and the framework's render gateway builds one from its
:class:`nsplat.render.renderer.RenderConfig` (whose op fields are exactly these, with these defaults), so the
settings of :func:`nsplat.ops.splat` are defined, defaulted and validated in this one place.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from .validation import COMPOSITES, check_backface_cull, check_deterministic, check_range, check_sampling


@dataclasses.dataclass(frozen=True)
class SplatSettings:
    """Every setting of :func:`nsplat.ops.splat` except the per-call ones (tensors, image size, background,
    seed); validated at construction with the op's own checks (``TypeError``/``ValueError``).

    Attributes:
        samples: per-pixel sample size m. eps: probability bound that a pixel's sample differs from exact SPS.
        estimator: "ht" | "ht-pips" | "paper" | "sampled". composite: "alpha" | "additive".
        near, far: clipping on the centre depth. lowpass: screen-space low-pass variance (px²).
        hermite_order, hermite_tol: the sampler's Hermite expansions.
        deterministic: fixed-order backward (False: atomic-scatter CPU backward).
        stratified: stratified uniforms across pixels.
        backface_cull: cull surfels facing away from each camera (default: two-sided).
    """

    samples: int = 40
    eps: float = 0.01
    estimator: str = "ht"
    composite: str = "alpha"
    near: float = 0.01
    far: float = 1e10
    lowpass: float = 1.0
    hermite_order: int = 8
    hermite_tol: float = 1e-3
    deterministic: bool = True
    stratified: bool = False
    backface_cull: bool = False

    def __post_init__(self) -> None:
        check_sampling(samples=self.samples, eps=self.eps, estimator=self.estimator, seed=0,
                       hermite_order=self.hermite_order, hermite_tol=self.hermite_tol, stratified=self.stratified)
        check_range(near=self.near, far=self.far, lowpass=self.lowpass)
        if self.composite not in COMPOSITES:
            raise ValueError(f"composite: expected one of {COMPOSITES}, got {self.composite!r}")
        check_deterministic(self.deterministic)
        check_backface_cull(self.backface_cull)

    def kwargs(self) -> dict[str, Any]:
        """The settings as keyword arguments of :func:`nsplat.ops.splat`."""
        return dataclasses.asdict(self)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The setting names (the op fields a config holding these settings must have)."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def of(cls, obj: object) -> "SplatSettings":
        """The settings read from the same-named attributes of ``obj`` (e.g. a render config)."""
        return cls(**{name: getattr(obj, name) for name in cls.names()})
