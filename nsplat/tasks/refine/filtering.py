"""Outlier filter: remove points whose accumulated photometric error is improbable.

Per point ``k`` we accumulate, over rendered views and valid reference pixels ``x``, its compositing
weight ``W_k = Σ_x w_k(x)`` and its weighted photometric error

    E_k = Σ_x w_k(x) · ‖f_k − I_ref(x)‖² / C

where ``w_k(x) = α_k(x) T_k(x)`` is the point's contribution to pixel ``x`` and ``f_k`` its rendered
colour (C channels): how badly the point's own colour explains the reference where it is visible. A
floating outlier shows its wrong colour where the reference shows the surface behind it; a surface
point occluded by an outlier still matches the reference where it is visible, so (unlike the pixel
residual) the measure does not smear an outlier's error onto its neighbours. Expanding the square,
``E_k = ‖f_k‖² W_k − 2 f_k·R_k + Q_k`` with ``R_k = Σ_x w_k(x) I_ref(x)`` and ``Q_k = Σ_x w_k(x)
‖I_ref(x)‖²``: sums linear in the weights, read off the renderer by autograd. Rendering a probe
feature ``g ≡ 1`` (C + 2 channels) gives ``∂/∂g_k Σ_x G(x)·I(x) = Σ_x w_k(x) G(x)`` for
``G = (1, I_ref, ‖I_ref‖²)``, so the same code serves the dense renderer (exact sums) and the sampled
op (its gradient estimator's estimate of them).

Decision: the mean error of a point, ``ē_k = E_k / W_k`` (optionally ``log ē_k``), is compared to the
robust distribution over all points seen with ``W_k ≥ min_weight``: median ``μ`` and scaled MAD
``σ = 1.4826·MAD``. A point is an outlier when the one-sided normal tail probability of its z-score,
``P(Z ≥ (ē_k − μ)/σ)``, is below ``p_value``. Points seen less than ``min_weight`` are not judged.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Literal

import torch

from nsplat.config import require_fields


@dataclasses.dataclass
class FilterConfig:
    """Outlier-filter settings.

    Attributes:
        enabled: run the filter at all.
        start: first optimisation step at which the filter runs.
        every: run every this many steps (from ``start``); 0 runs it only once at ``start``.
        p_value: points whose error tail probability is below this are removed.
        min_weight: points with accumulated weight ``W_k`` below this are not judged (kept).
        transform: ``"log"`` judges ``log ē_k`` (errors are positive and skewed), ``"none"`` ``ē_k``.
        max_fraction: never remove more than this fraction of the judged points in one pass
            (the most improbable first).
    """

    enabled: bool = True
    start: int = 50
    every: int = 100
    p_value: float = 1e-3
    min_weight: float = 0.5
    transform: Literal["log", "none"] = "log"
    max_fraction: float = 0.1

    def __post_init__(self) -> None:
        require_fields(self, p_value="open", min_weight=">=0", max_fraction="prob", start=">=0", every=">=0")

    def due(self, step: int) -> bool:
        """Whether the filter runs after optimisation step ``step``."""
        if not self.enabled or step < self.start:
            return False
        if self.every == 0:
            return step == self.start
        return (step - self.start) % self.every == 0


def point_errors(render_probe: Callable[[torch.Tensor], torch.Tensor], colours: torch.Tensor,
                 reference: torch.Tensor, mask: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-point weighted photometric error and weight of one batch of views.

    Args:
        render_probe: renders per-point features ``[N, C+2]`` into images ``[B, H, W, C+2]`` with the
            current geometry and cameras (any background; it does not reach the sums).
        colours: ``[N, C]`` the points' rendered colours in these views.
        reference: ``[B, H, W, C]`` reference images.
        mask: ``[B, H, W]`` valid reference pixels (bool or 0/1); ``None``: all valid.

    Returns:
        ``(E [N], W [N])`` (detached, see the module docstring).
    """
    N, C = colours.shape
    if reference.shape[-1] != C:
        raise ValueError(f"reference has {reference.shape[-1]} channels, colours {C}")
    ref = reference.detach()
    m = torch.ones(ref.shape[:-1], dtype=ref.dtype, device=ref.device) if mask is None else mask.to(ref.dtype)
    if m.shape != ref.shape[:-1]:
        raise ValueError(f"mask {tuple(m.shape)} does not match reference {tuple(ref.shape[:-1])}")
    with torch.enable_grad():
        probe = torch.ones(N, C + 2, dtype=ref.dtype, device=ref.device, requires_grad=True)
        image = render_probe(probe)
        if image.shape[:-1] != ref.shape[:-1] or image.shape[-1] != C + 2:
            raise ValueError(f"render_probe returned {tuple(image.shape)}, expected "
                             f"{tuple(ref.shape[:-1]) + (C + 2,)}")
        g = torch.cat([m[..., None], ref * m[..., None], (ref * ref).sum(-1, keepdim=True) * m[..., None]], -1)
        (grad,) = torch.autograd.grad((image * g).sum(), probe)
    W, R, Q = grad[:, 0], grad[:, 1:C + 1], grad[:, C + 1]
    f = colours.detach().to(grad.dtype)
    E = ((f * f).sum(-1) * W - 2.0 * (f * R).sum(-1) + Q) / C
    return E.clamp_min(0.0), W


class ErrorAccumulator:
    """Running sums ``E [N]`` and ``W [N]`` over views; re-indexed when points are removed."""

    def __init__(self, num_points: int, device: torch.device | str = "cpu") -> None:
        self.error = torch.zeros(num_points, dtype=torch.float64, device=device)
        self.weight = torch.zeros(num_points, dtype=torch.float64, device=device)

    def add(self, error: torch.Tensor, weight: torch.Tensor) -> None:
        """Add one batch's ``E [N]`` and ``W [N]``."""
        if error.shape != self.error.shape or weight.shape != self.weight.shape:
            raise ValueError(f"expected [{self.error.numel()}] sums, got {tuple(error.shape)}, "
                             f"{tuple(weight.shape)}")
        self.error += error.to(self.error)
        self.weight += weight.to(self.weight)

    def keep(self, keep: torch.Tensor) -> None:
        """Drop the sums of removed points (``keep [N]`` bool)."""
        self.error, self.weight = self.error[keep], self.weight[keep]

    def reset(self) -> None:
        """Zero the sums."""
        self.error.zero_()
        self.weight.zero_()

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"error": self.error.clone(), "weight": self.weight.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.error = state["error"].to(self.error.device)
        self.weight = state["weight"].to(self.weight.device)


def improbable(error: torch.Tensor, weight: torch.Tensor, cfg: FilterConfig) -> torch.Tensor:
    """Outlier decision of the filter (see the module docstring).

    Args:
        error: ``[N]`` accumulated ``E_k``. weight: ``[N]`` accumulated ``W_k``.
        cfg: the filter settings.

    Returns:
        ``[N]`` bool, True for the points to remove.
    """
    judged = weight >= max(cfg.min_weight, 1e-12)
    out = torch.zeros_like(judged)
    if int(judged.sum()) < 3:
        return out
    mean = error[judged] / weight[judged]
    if cfg.transform == "log":
        mean = torch.log(mean.clamp_min(1e-12))
    mu = mean.median()
    sigma = 1.4826 * (mean - mu).abs().median()
    if not torch.isfinite(sigma) or sigma <= 0:
        return out
    z = (mean - mu) / sigma
    tail = 0.5 * torch.erfc(z / math.sqrt(2.0))
    bad = tail < cfg.p_value
    limit = int(math.floor(cfg.max_fraction * mean.numel()))
    if int(bad.sum()) > limit:
        order = torch.argsort(z, descending=True)
        bad = torch.zeros_like(bad)
        bad[order[:limit]] = True
    out[judged.nonzero()[:, 0]] = bad
    return out
