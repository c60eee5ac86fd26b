"""The outlier filter (nsplat.tasks.refine.filtering) removes planted outliers and keeps the surface."""
import math

import pytest
import torch

from nsplat.cameras import intrinsics, look_at
from nsplat.config import ConfigError
from nsplat.ops import splat_dense
from nsplat.tasks.refine.filtering import ErrorAccumulator, FilterConfig, improbable, point_errors


def _plane(n_side: int = 16, size: float = 1.0):
    """A textured square plane of surfels at z = 0 (side ``size``, a smooth colour pattern)."""
    s = ((torch.arange(n_side, dtype=torch.float64) + 0.5) / n_side - 0.5) * size
    y, x = torch.meshgrid(s, s, indexing="ij")
    means = torch.stack([x, y, torch.zeros_like(x)], -1).reshape(-1, 3)
    normals = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(means).clone()
    col = torch.stack([0.5 + 0.4 * torch.sin(6 * x), 0.5 + 0.4 * torch.cos(5 * y), 0.5 + 0 * x], -1)
    return means, normals, col.reshape(-1, 3), 0.7 * size / n_side


def _cameras():
    eye = torch.tensor([[0.0, 0.0, 1.6], [0.5, 0.2, 1.5], [-0.4, -0.4, 1.5]], dtype=torch.float64)
    V = look_at(eye, torch.zeros_like(eye), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    K = intrinsics(28.0, 28.0, 16.0, 16.0, batch=3, dtype=torch.float64)
    return V, K


def test_filter_removes_planted_outliers():
    # the plane fills every view (no edges against the background)
    means, normals, colours, scale = _plane(24, 2.4)
    V, K = _cameras()
    n = means.shape[0]
    ref = splat_dense(means, normals, torch.full((n, 2), scale, dtype=torch.float64),
                      torch.full((n,), 0.95, dtype=torch.float64), colours, V, K, 32, 32).image
    # plant 12 floating points in front of the plane with wrong colours
    g = torch.Generator().manual_seed(3)
    k = 12
    out_means = torch.cat([(torch.rand(k, 2, generator=g, dtype=torch.float64) - 0.5) * 0.7,
                           0.15 + 0.3 * torch.rand(k, 1, generator=g, dtype=torch.float64)], -1)
    out_cols = torch.rand(k, 3, generator=g, dtype=torch.float64)
    out_cols[:, 2] = 1.0 - out_cols[:, 2] * 0.2  # far from the plane's blue channel of 0.5
    M = torch.cat([means, out_means])
    N = torch.cat([normals, normals[:k]])
    C = torch.cat([colours, out_cols])
    S = torch.full((n + k, 2), scale, dtype=torch.float64)
    Op = torch.full((n + k,), 0.95, dtype=torch.float64)

    mask = torch.ones(ref.shape[:-1], dtype=torch.bool)
    mask[:, :2] = False  # an invalid band: must not count
    acc = ErrorAccumulator(n + k)
    for b in range(3):  # accumulate view by view
        E, W = point_errors(lambda f: splat_dense(M, N, S, Op, f, V[b:b + 1], K[b:b + 1], 32, 32).image,
                            C, ref[b:b + 1], mask[b:b + 1])
        acc.add(E, W)
    bad = improbable(acc.error, acc.weight, FilterConfig(p_value=1e-3, min_weight=0.05))
    planted = torch.zeros(n + k, dtype=torch.bool)
    planted[n:] = True
    assert bool(bad[planted].all()), f"missed outliers: {(~bad[planted]).nonzero().flatten().tolist()}"
    assert int(bad[~planted].sum()) <= 0.05 * n


def test_point_errors_match_explicit_sums():
    # E_k = sum_x w_k(x) |f_k - ref(x)|^2 / C and W_k = sum_x w_k(x), with w_k from one-hot renders
    # (additive compositing: w_k(x) = alpha_k(x)); the mask removes pixels from both sums.
    means, normals, colours, scale = _plane(4)
    V, K = _cameras()
    n = means.shape[0]
    S = torch.full((n, 2), scale, dtype=torch.float64)
    Op = torch.full((n,), 0.5, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(3, 32, 32, 3, generator=g, dtype=torch.float64)
    mask = torch.rand(3, 32, 32, generator=g) > 0.3
    E, W = point_errors(lambda f: splat_dense(means, normals, S, Op, f, V, K, 32, 32, composite="additive").image,
                        colours, ref, mask)
    for k in (0, 5, 15):
        onehot = torch.zeros(n, 1, dtype=torch.float64)
        onehot[k] = 1.0
        w = splat_dense(means, normals, S, Op, onehot, V, K, 32, 32, composite="additive").image[..., 0] * mask
        sq = ((colours[k] - ref) ** 2).mean(-1)
        assert E[k].item() == pytest.approx(float((w * sq).sum()), rel=1e-9)
        assert W[k].item() == pytest.approx(float(w.sum()), rel=1e-9)


def test_improbable_statistics_and_limits():
    g = torch.Generator().manual_seed(1)
    weight = torch.ones(1000, dtype=torch.float64)
    error = torch.exp(0.2 * torch.randn(1000, generator=g, dtype=torch.float64)) * 0.05
    error[:5] = 2.0  # planted: 40x the typical error
    weight[10] = 0.0  # unseen: never judged
    error[10] = 100.0
    bad = improbable(error, weight, FilterConfig(p_value=1e-4, min_weight=0.5))
    assert bad[:5].all() and not bad[10]
    assert int(bad[5:].sum()) <= 2
    capped = improbable(error, weight, FilterConfig(p_value=1e-4, min_weight=0.5, max_fraction=0.002))
    assert int(capped.sum()) == 1
    plain = improbable(error, weight, FilterConfig(p_value=1e-4, min_weight=0.5, transform="none"))
    assert plain[:5].all() and int(plain[5:].sum()) <= 2


def test_config_validation_and_schedule():
    with pytest.raises(ConfigError, match="p_value"):
        FilterConfig(p_value=1.5)
    with pytest.raises(ConfigError, match="max_fraction"):
        FilterConfig(max_fraction=0.0)
    cfg = FilterConfig(start=10, every=5)
    assert [s for s in range(30) if cfg.due(s)] == [10, 15, 20, 25]
    assert [s for s in range(30) if FilterConfig(start=7, every=0).due(s)] == [7]
    assert not FilterConfig(enabled=False).due(50)
    assert math.isfinite(FilterConfig().p_value)
