"""The estimators' bias, measured against the dense oracle's exact gradient (docs/op.md "Estimators").

With additive compositing the dense gradient is a plain sum over points, so an unbiased estimator's mean
must converge to it. Each check draws thousands of sampled gradients of a fixed linear loss in float64
(:func:`nsplat.ops.diagnostics.estimator_study`, batch means) and tests the standardised errors
``z = (mean − dense) / se``: for an unbiased estimator ``z`` is a t-statistic, so the mean of ``z²`` stays
near 1 however many draws are taken, while any bias makes it grow in proportion to the number of draws.
The πps-weighted ``"ht-pips"`` is included to show that the test detects the bias it is meant to catch.
"""
from __future__ import annotations

import math

import pytest
import torch

from nsplat.ops.diagnostics import estimator_study
from tests.conftest import make_cameras, make_scene

W = H = 10
GROUPS = 40  # t-statistics with 39 degrees of freedom: E[z²] = 39/37 ≈ 1.05


def skewed_scene(N: int = 25, seed: int = 4) -> dict[str, torch.Tensor]:
    """Random surfels whose sizes span a factor 12 (log-uniform), so per-pixel λ are strongly skewed."""
    sc = make_scene(N, seed, dtype=torch.float64, spread=0.35)
    g = torch.Generator().manual_seed(seed + 1)
    lo, hi = math.log(0.02), math.log(0.25)
    s = torch.exp(lo + (hi - lo) * torch.rand(N, generator=g, dtype=torch.float64))
    sc["scales"] = torch.stack([s, s * (0.6 + 0.4 * torch.rand(N, generator=g, dtype=torch.float64))], 1)
    return sc


def _study(estimator: str, m: int, per_group: int, stratified: bool = False):
    sc = skewed_scene()
    V, K = make_cameras(1, W, H, dtype=torch.float64)
    w = torch.randn(H, W, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    return estimator_study(sc, V, K, W, H, w, estimator=estimator, samples=m, groups=GROUPS, per_group=per_group,
                           stratified=stratified)


@pytest.mark.parametrize("m", [1, 2, 4, 8])
def test_ht_gradient_is_unbiased_in_additive_mode(m):
    """"ht" (priority-sampling threshold weights): 16 000 draws, mean z² ≈ 1 and no outlier beyond the
    family-wise bound (~300 t-statistics: |z| <= 5.5), the projected relative bias within 4 SE. Groups of 400
    draws: at m = 1 the weights 1/π are heavy-tailed, and group means of 100 draws are still far enough from
    normal to put the mean z² of an unbiased estimator near 1.6 (it then falls with more draws, where a bias
    would make it grow: test_ht_z2_does_not_grow_with_draws)."""
    st = _study("ht", m, per_group=400)
    z = st.z()
    assert float((z ** 2).mean()) < 1.6, float((z ** 2).mean())
    assert float(z.abs().max()) < 5.5, float(z.abs().max())
    b, se = st.projected_bias()
    assert abs(b) < 4 * se, (b, se)


def test_ht_z2_does_not_grow_with_draws():
    """Four times the draws: an unbiased estimator's mean z² stays near 1 (a biased one's quadruples)."""
    small, large = _study("ht", 4, per_group=50), _study("ht", 4, per_group=200)
    z_small, z_large = small.z(), large.z()
    assert float((z_small ** 2).mean()) < 1.6 and float((z_large ** 2).mean()) < 1.6
    b, se = large.projected_bias()
    assert se < 0.01 and abs(b) < 4 * se, (b, se)  # a 1 % bias along the gradient would be > 4 SE here


def test_stratified_draws_keep_ht_unbiased():
    """Stratified uniforms across pixels change the joint law of the draws, not the per-pixel marginals."""
    st = _study("ht", 4, per_group=50, stratified=True)
    z = st.z()
    assert float((z ** 2).mean()) < 1.6 and float(z.abs().max()) < 5.5


@pytest.mark.parametrize("m", [2, 4, 8])
def test_pips_weights_bias_is_detected(m):
    """The same test on the πps weights ("ht-pips", the op's former "ht") fails: mean z² far above 1 and
    growing with the number of draws — SPS includes points only approximately with the πps targets."""
    small, large = _study("ht-pips", m, per_group=50), _study("ht-pips", m, per_group=200)
    z2_small, z2_large = float((small.z() ** 2).mean()), float((large.z() ** 2).mean())
    assert z2_large > 4.0, z2_large
    assert z2_large > 2.0 * z2_small, (z2_small, z2_large)
