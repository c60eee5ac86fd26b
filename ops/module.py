"""``nn.Module`` wrapper of :func:`nsplat.ops.splat` holding the op's settings."""
from __future__ import annotations

import torch
from torch import nn

from .functional import splat
from .output import SplatOutput
from .validation import COMPOSITES, check_deterministic, check_range, check_sampling


class Splatter(nn.Module):
    """Sampled EWA surface splatting as a layer.

    Holds the sampling/compositing settings; every call without an explicit ``seed`` uses a fresh
    seed (``base_seed + number of previous calls``) so that successive training steps draw
    independent samples while a run stays reproducible. The call counter is saved in the state dict.

    Example:
        >>> splatter = Splatter(samples=40, eps=0.01)
        >>> out = splatter(means, normals, scales, opacities, features, viewmats, Ks, 128, 128)
        >>> out.image.shape   # [B, 128, 128, C]
    """

    def __init__(self, samples: int = 40, eps: float = 0.01, estimator: str = "ht", composite: str = "alpha",
                 near: float = 0.01, far: float = 1e10, lowpass: float = 1.0, base_seed: int = 0,
                 hermite_order: int = 8, hermite_tol: float = 1e-3, deterministic: bool = True,
                 stratified: bool = False) -> None:
        super().__init__()
        check_sampling(samples=samples, eps=eps, estimator=estimator, seed=base_seed, hermite_order=hermite_order,
                       hermite_tol=hermite_tol, stratified=stratified)  # fail at construction, not at the first forward
        check_range(near=near, far=far, lowpass=lowpass)
        if composite not in COMPOSITES:
            raise ValueError(f"composite: expected one of {COMPOSITES}, got {composite!r}")
        check_deterministic(deterministic)
        self.samples, self.eps, self.estimator, self.composite = samples, eps, estimator, composite
        self.near, self.far, self.lowpass, self.base_seed = near, far, lowpass, base_seed
        self.hermite_order, self.hermite_tol = hermite_order, hermite_tol
        self.deterministic = deterministic  # False: faster atomic-scatter CPU backward (see splat)
        self.stratified = stratified  # stratified uniforms across pixels (see splat)
        self.register_buffer("calls", torch.zeros((), dtype=torch.long), persistent=True)

    def forward(self, means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                background: torch.Tensor | None = None, seed: int | None = None) -> SplatOutput:
        """Render ``[B,H,W,C]`` feature images; shapes as in :func:`nsplat.ops.splat`."""
        if seed is None:
            seed = self.base_seed + int(self.calls)
            self.calls += 1
        return splat(means, normals, scales, opacities, features, viewmats, Ks, width, height, samples=self.samples,
                     eps=self.eps, estimator=self.estimator, composite=self.composite, background=background,
                     near=self.near, far=self.far, lowpass=self.lowpass, seed=seed,
                     hermite_order=self.hermite_order, hermite_tol=self.hermite_tol,
                     deterministic=self.deterministic, stratified=self.stratified)

    def extra_repr(self) -> str:
        return (f"samples={self.samples}, eps={self.eps}, estimator={self.estimator!r}, "
                f"composite={self.composite!r}, lowpass={self.lowpass}")
