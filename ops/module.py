"""``nn.Module`` wrapper of :func:`nsplat.ops.splat` holding the op's settings (:class:`SplatSettings`)."""
from __future__ import annotations

import torch
from torch import nn

from .functional import splat
from .output import SplatOutput
from .settings import SplatSettings
from .validation import check_sampling


class Splatter(nn.Module):
    """Sampled EWA surface splatting as a layer.

    Holds the op's settings as one :class:`SplatSettings` (``splatter.settings``; each also reads as an
    attribute, ``splatter.samples``); every call without an explicit ``seed`` uses a fresh
    seed (``base_seed + number of previous calls``) so that successive training steps draw
    independent samples while a run stays reproducible. The call counter is saved in the state dict and stays on
    the host when the module moves to a device.

    Example:
        >>> splatter = Splatter(samples=40, eps=0.01)
        >>> out = splatter(means, normals, scales, opacities, features, viewmats, Ks, 128, 128)
        >>> out.image.shape   # [B, 128, 128, C]
    """

    def __init__(self, samples: int = 40, eps: float = 0.01, estimator: str = "ht", composite: str = "alpha",
                 near: float = 0.01, far: float = 1e10, lowpass: float = 1.0, base_seed: int = 0,
                 hermite_order: int = 8, hermite_tol: float = 1e-3, deterministic: bool = True,
                 stratified: bool = False, backface_cull: bool = False, *,
                 settings: SplatSettings | None = None) -> None:
        """The settings are the keyword arguments, or ``settings`` (then the other op arguments are ignored)."""
        super().__init__()
        if settings is None:  # validated at construction, not at the first forward
            settings = SplatSettings(samples=samples, eps=eps, estimator=estimator, composite=composite, near=near,
                                     far=far, lowpass=lowpass, hermite_order=hermite_order, hermite_tol=hermite_tol,
                                     deterministic=deterministic, stratified=stratified,
                                     backface_cull=backface_cull)
        elif not isinstance(settings, SplatSettings):
            raise TypeError(f"settings: expected a SplatSettings, got {type(settings).__name__}")
        check_sampling(samples=settings.samples, eps=settings.eps, estimator=settings.estimator, seed=base_seed,
                       hermite_order=settings.hermite_order, hermite_tol=settings.hermite_tol)
        self.settings = settings
        self.base_seed = base_seed
        self.register_buffer("calls", torch.zeros((), dtype=torch.long), persistent=True)

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202 - nn.Module's signature
        """Moves the module (``.to``, ``.cuda``, ...) but keeps ``calls`` on the host: the sampler reads each call's
        seed there, and a counter on a GPU would make that read a synchronisation."""
        calls = self.calls
        super()._apply(fn, recurse)
        self._buffers["calls"] = calls
        return self

    def forward(self, means: torch.Tensor, normals: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                background: torch.Tensor | None = None, seed: int | None = None) -> SplatOutput:
        """Render ``[B,H,W,C]`` feature images; shapes as in :func:`nsplat.ops.splat`."""
        if seed is None:  # a tensor seed: no .item(), so torch.compile traces this without a graph break
            seed = self.calls + self.base_seed
            self.calls += 1
        return splat(means, normals, scales, opacities, features, viewmats, Ks, width, height, background=background,
                     seed=seed, **self.settings.kwargs())

    def extra_repr(self) -> str:
        return (f"samples={self.samples}, eps={self.eps}, estimator={self.estimator!r}, "
                f"composite={self.composite!r}, lowpass={self.lowpass}")


def _setting(name: str) -> property:
    return property(lambda self: getattr(self.settings, name),
                    doc=f"``settings.{name}`` (read-only; replace ``settings`` to change it).")


for _name in SplatSettings.names():  # splatter.samples, splatter.eps, ... read the settings
    setattr(Splatter, _name, _setting(_name))
del _name
