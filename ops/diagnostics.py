"""Monte-Carlo diagnostics of the sampled op's gradient estimators against the dense oracle.

:func:`estimator_study` draws many independent sampled gradients of a fixed linear loss
``L = Σ w · image`` and compares their mean with the exact gradient of :func:`splat_dense`. Draws are
made in groups: one call renders ``per_group`` copies of the camera (each copy has its own random
stream), so a group's gradient is the mean of ``per_group`` independent estimates, and the ``groups``
group means are i.i.d. ("batch means"). Their standard error is robust to the heavy tails that
Horvitz–Thompson weights can have on low-coverage pixels.

Used by ``tests/test_op_unbiased.py`` (the bias test in CI) and ``benchmarks/estimators.py`` (the table
of bias and variance per estimator and sample size).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .functional import splat
from .reference import splat_dense

PARAMS = ("means", "normals", "scales", "opacities", "features")


@dataclass
class EstimatorStudy:
    """Result of :func:`estimator_study`; every tensor is ``[D]`` over the flattened parameters ``PARAMS``.

    Attributes:
        dense: exact gradient. mean: mean of the sampled gradients. se: standard error of ``mean``
        (batch means). std: standard deviation of one single-camera estimate (``se·sqrt(draws)``).
        draws: number of single-camera estimates. names: parameter name per entry.
    """

    dense: torch.Tensor
    mean: torch.Tensor
    se: torch.Tensor
    std: torch.Tensor
    draws: int
    names: list[str]

    def z(self, floor: float = 1e-12) -> torch.Tensor:
        """``[D']`` standardised errors ``(mean − dense)/se`` over entries whose ``se`` exceeds ``floor``
        times the largest (entries that are identically zero in every draw carry no information)."""
        keep = self.se > floor * float(self.se.max())
        return (self.mean - self.dense)[keep] / self.se[keep]

    def relative_bias(self) -> tuple[float, float]:
        """``(‖mean − dense‖ / ‖dense‖, its standard error scale ‖se‖ / ‖dense‖)``."""
        nd = float(self.dense.norm())
        return float((self.mean - self.dense).norm()) / nd, float(self.se.norm()) / nd

    def projected_bias(self) -> tuple[float, float]:
        """Bias along the dense gradient, relative: ``(⟨mean − dense, dense⟩ / ‖dense‖², its standard error)``.
        A 1 % over- or under-estimation of the whole gradient reads 0.01 here."""
        nd2 = float((self.dense ** 2).sum())
        return float(((self.mean - self.dense) * self.dense).sum()) / nd2, float((self.se * self.dense).norm()) / nd2

    def cosine(self) -> float:
        """Cosine between the mean sampled gradient and the dense one (direction bias; 1 = none)."""
        return float(torch.nn.functional.cosine_similarity(self.mean, self.dense, dim=0))

    def relative_std(self) -> float:
        """Root-mean-square single-draw standard deviation relative to the dense gradient's RMS."""
        return float(self.std.norm()) / float(self.dense.norm())


def _flat(grads: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat([g.reshape(-1) for g in grads])


def estimator_study(scene: dict[str, torch.Tensor], viewmat: torch.Tensor, K: torch.Tensor, width: int,
                    height: int, weights: torch.Tensor, *, estimator: str, samples: int, composite: str = "additive",
                    groups: int = 40, per_group: int = 25, eps: float = 1e-6, stratified: bool = False,
                    seed: int = 0, background: torch.Tensor | None = None) -> EstimatorStudy:
    """Mean and standard error of ``groups·per_group`` sampled gradients of ``Σ weights·image``.

    Args:
        scene: ``means [N,3]``, ``normals [N,3]``, ``scales [N,2]``, ``opacities [N]``, ``features [N,C]``.
        viewmat: ``[1,4,4]``. K: ``[1,3,3]``. weights: ``[H,W,C]`` fixed loss weights.
        estimator, samples, composite, eps, stratified: the op's settings (:func:`nsplat.ops.splat`).
        groups, per_group: number of group means and single-camera draws per group. seed: first seed.
        background: ``[C]`` or None.

    Returns:
        :class:`EstimatorStudy` with the dense gradient as reference.
    """
    leaves = [scene[k].detach().clone().requires_grad_(True) for k in PARAMS]
    out = splat_dense(*leaves, viewmat, K, width, height, composite=composite, background=background)
    dense = _flat(torch.autograd.grad((out.image[0] * weights).sum(), leaves))
    V = viewmat.expand(per_group, 4, 4).contiguous()
    Ks = K.expand(per_group, 3, 3).contiguous()
    means = []
    for g in range(groups):
        out = splat(*leaves, V, Ks, width, height, samples=samples, eps=eps, estimator=estimator,
                    composite=composite, seed=seed + g, stratified=stratified, background=background)
        loss = (out.image * weights).sum() / per_group
        means.append(_flat(torch.autograd.grad(loss, leaves)))
    stack = torch.stack(means)
    mean = stack.mean(0)
    se = stack.std(0) / groups ** 0.5
    names = [k for k in PARAMS for _ in range(scene[k].numel())]
    return EstimatorStudy(dense=dense, mean=mean, se=se, std=se * (groups * per_group) ** 0.5,
                          draws=groups * per_group, names=names)
