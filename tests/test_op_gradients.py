"""Gradients: gradcheck of the oracle and the compositor, sampled vs dense, the estimators' definitions and
the expectation of the Horvitz–Thompson estimators (docs/method.md "Backward")."""
from __future__ import annotations

import pytest
import torch
from scipy.stats import norm

from nsplat.ops import composite_sample, project, sample, splat, splat_dense
from nsplat.ops.reference import (
    pips_probabilities,
    pixel_centres,
    pixel_rays,
    size_measures,
    splat_alpha,
    splat_depth,
    sps_expectation_weights,
)
from tests.conftest import make_cameras, make_scene

NAMES = ("means", "normals", "scales", "opacities", "features", "viewmats", "background")


def _params(sc, V, bg):
    return [t.clone().requires_grad_() for t in (sc["means"], sc["normals"], sc["scales"], sc["opacities"],
                                                 sc["features"], V, bg)]


def test_gradcheck_dense_oracle():
    sc = make_scene(4, 0, C=2, dtype=torch.float64, spread=0.2)
    V, K = make_cameras(2, 6, 5, dtype=torch.float64, focal=6.0)
    bg = torch.tensor([0.2, 0.6], dtype=torch.float64)

    last_row = V[:, 3:, :]

    def fn(*p):
        viewmats = torch.cat([p[5], last_row], dim=1)  # gradcheck perturbs only the 3x4 part
        out = splat_dense(*p[:5], viewmats, K, 6, 5, background=p[6])
        return out.image, out.alpha, out.depth

    params = _params(sc, V, bg)
    params[5] = V[:, :3, :].clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("composite,estimator", [("alpha", "sampled"), ("additive", "ht")])
def test_gradcheck_compositor_given_fixed_sample(composite, estimator):
    """The native compositor's backward equals finite differences for a fixed sample (π fixed too).

    These are the combinations whose backward is the derivative of the forward: alpha blending with the
    plain estimator, and the HT-weighted additive sum with "ht". The other combinations reweight terms by
    design and are checked through the full-sample equality and the unbiasedness test."""
    sc = make_scene(12, 1, C=2, dtype=torch.float64, spread=0.25)
    V, K = make_cameras(1, 7, 6, dtype=torch.float64, focal=7.0)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    idx, probs, _, _ = sample(proj, K, 7, 6, samples=4, seed=2)
    assert bool((probs[idx >= 0] < 1).any()), "the fixed sample should be a proper subsample"
    leaves = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, proj.amps, proj.normals_cam,
                                                             proj.plane_offsets, proj.depths, sc["features"])]
    bg = torch.tensor([0.3, 0.7], dtype=torch.float64, requires_grad=True)

    def fn(mu, con, amp, nrm, off, zc, feat, bgv):
        p = type(proj)(mu, con, amp, nrm, off, zc, proj.sigma2, proj.valid)
        return composite_sample(p, feat, K, idx, probs, background=bgv, composite=composite, estimator=estimator)

    assert torch.autograd.gradcheck(fn, (*leaves, bg), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("composite", ["alpha", "additive"])
@pytest.mark.parametrize("estimator", ["ht", "paper", "sampled"])
def test_full_sample_gradients_equal_dense(composite, estimator):
    """With samples >= N (π = 1) "ht" and "sampled" gradients equal the dense autograd gradients for
    every parameter; "paper" equals them divided by |N_k| (checked on the features)."""
    W, H = 16, 12
    sc = make_scene(30, 2, C=3, dtype=torch.float64)
    V, K = make_cameras(2, W, H, dtype=torch.float64)
    bg = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    wi, wa, wd = (torch.randn(2, H, W, c, generator=g, dtype=torch.float64) for c in (3, 1, 1))

    def loss(o):
        return (o.image * wi).sum() + (o.alpha * wa).sum() + (o.depth * wd).sum()

    ps = _params(sc, V, bg)
    out = splat(*ps[:6], K, W, H, samples=30, composite=composite, estimator=estimator, background=ps[6])
    got = torch.autograd.grad(loss(out), ps)
    pd = _params(sc, V, bg)
    ref = torch.autograd.grad(loss(splat_dense(*pd[:6], K, W, H, composite=composite, background=pd[6])), pd)
    if estimator == "paper":
        counts = torch.stack([torch.bincount(out.indices[b][out.indices[b] >= 0].long(), minlength=30)
                              for b in range(2)])
        assert bool((counts > 0).all())
        # features are shared by the cameras: Σ_b g_b / |N_kb|; check on a single camera's share instead
        one = _params(sc, V[:1], bg)
        o1 = splat(*one[:6], K[:1], W, H, samples=30, composite=composite, estimator="paper", background=one[6])
        g1 = torch.autograd.grad(loss_one := (o1.image * wi[:1]).sum(), one[4])[0]
        d1 = _params(sc, V[:1], bg)
        r1 = torch.autograd.grad((splat_dense(*d1[:6], K[:1], W, H, composite=composite,
                                              background=d1[6]).image * wi[:1]).sum(), d1[4])[0]
        del loss_one
        assert torch.allclose(g1 * counts[0, :, None], r1, rtol=1e-6, atol=1e-9)
        return
    for name, a, b in zip(NAMES, got, ref):
        scale = float(b.abs().max())
        assert torch.allclose(a, b, rtol=0, atol=1e-6 * max(scale, 1.0)), (name, float((a - b).abs().max()))


def _expected_additive_loss(sc_params, K, W, H, ratio, wi, wa, wd):
    """E[L] under SPS for the additive op and a linear loss: the dense additive render with every term
    weighted by P_k/π_k (exact SPS inclusion over πps probability), differentiable by autograd."""
    means, normals, scales, opac, feats, V, bg = sc_params
    proj = project(means, normals, scales, opac, V, K, near=0.01, far=1e10, lowpass=1.0)
    pix = pixel_centres(W, H, means.dtype, means.device)
    rays = pixel_rays(K, W, H).reshape(V.shape[0], -1, 3)
    total = 0
    for b in range(V.shape[0]):
        a = splat_alpha(pix, proj.means2d[b], proj.conics[b], proj.amps[b]) * ratio[b]
        d = splat_depth(rays[b], proj.normals_cam[b], proj.plane_offsets[b], proj.depths[b])
        img = a @ feats + (1 - a.sum(1, keepdim=True)) * bg
        total = total + (img * wi[b].reshape(-1, 3)).sum() + (a.sum(1) * wa[b].reshape(-1)).sum() \
            + ((a * d).sum(1) * wd[b].reshape(-1)).sum()
    return total


def test_pips_gradient_mean_is_the_exact_sps_expectation_in_additive_mode():
    """Mean of the "ht-pips" gradient over R seeds equals its exact expectation under SPS (from exact
    inclusion probabilities) within 4 standard errors, and the dense gradient within 4 SE plus exactly the
    gap implied by SPS's inclusion probabilities differing from πps, for positions, normals, scales,
    opacities, features, viewmats and background. (The exactly unbiased "ht" is tested against the dense
    gradient alone in tests/test_op_unbiased.py.)

    The loss weights are zero on the few pixels that have a certainty unit (πps = 1): there the op's π
    adapt to whether the unit was drawn, so a fixed-π expectation would not be an exact oracle.

    Every gradient element is compared, so the bound is the two-sided normal quantile of a family-wise error
    rate of 1e-3 over all of them (Bonferroni; ≈ 4.7 SE for the ~300 elements here), with R = 1000 seeds so
    that the heavy-tailed HT terms average to a near-normal mean."""
    W, H, m, R = 10, 8, 2, 1000
    sc = make_scene(16, 7, C=3, dtype=torch.float64, spread=0.2, scale=(0.1, 0.2))
    V, K = make_cameras(2, W, H, dtype=torch.float64, focal=10.0)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    lams = [size_measures(proj, b, W, H) for b in range(2)]
    keep = torch.stack([(pips_probabilities(lam, m).max(1).values < 1).reshape(H, W, 1) for lam in lams])
    assert float(keep.double().mean()) > 0.9
    g = torch.Generator().manual_seed(1)
    wi, wa, wd = (torch.randn(2, H, W, c, generator=g, dtype=torch.float64) * keep for c in (3, 1, 1))

    def loss(o):
        return (o.image * wi).sum() + (o.alpha * wa).sum() + (o.depth * wd).sum()

    runs = []
    for seed in range(R):
        ps = _params(sc, V, bg)
        # eps=1e-12: Λ̂ = Λ here, so the op's π are the πps probabilities (this test is about the estimator,
        # the ε-approximation of the sampler is tested in test_op_sampler.py)
        out = splat(*ps[:6], K, W, H, samples=m, eps=1e-12, composite="additive", estimator="ht-pips", seed=seed,
                    background=ps[6])
        runs.append([t.detach() for t in torch.autograd.grad(loss(out), ps)])
    pd = _params(sc, V, bg)
    dense = torch.autograd.grad(loss(splat_dense(*pd[:6], K, W, H, composite="additive", background=pd[6])), pd)
    ratio = torch.stack([sps_expectation_weights(lam, m) for lam in lams])
    pe = _params(sc, V, bg)
    expected = torch.autograd.grad(_expected_additive_loss(pe, K, W, H, ratio, wi, wa, wd), pe)
    z = float(norm.isf(1e-3 / (2 * sum(t.numel() for t in dense))))
    for i, name in enumerate(NAMES):
        stack = torch.stack([r[i] for r in runs])
        mean, se = stack.mean(0), stack.std(0) / R ** 0.5
        gap = (expected[i] - dense[i]).abs()
        roundoff = 1e-10 * float(dense[i].abs().max())
        ok = (mean - dense[i]).abs() <= z * se + gap + roundoff
        assert bool(ok.all()), (name, float(((mean - dense[i]).abs() - gap).max()), float(se.max()))
        # and the estimator's mean is the exact SPS expectation (no gap allowance)
        assert bool(((mean - expected[i]).abs() <= z * se + roundoff).all()), name


@pytest.mark.parametrize("shape,N", [((1, 4, 5, 3), 7), ((3, 8, 9, 5), 50), ((2, 1, 1, 4), 1), ((2, 3, 3, 2), 0)])
def test_backward_point_order_native_matches_definition(shape, N):
    """The backward's per-point order (native counting sort on the CPU) equals its definition: filled slots
    sorted by (point, camera, pixel, slot), with per-point segment offsets; and equals the device-sort path."""
    from nsplat.ops.functional import _entries_by_point, _entries_by_point_sorted

    g = torch.Generator().manual_seed(sum(shape) + N)
    idx = torch.randint(-1, max(N, 1), shape, generator=g, dtype=torch.int32)
    if N == 0:
        idx.fill_(-1)
    entries, seg = _entries_by_point(idx, N)
    flat = idx.reshape(-1).tolist()
    expected = sorted((k, s) for s, k in enumerate(flat) if k >= 0)  # s enumerates (camera, pixel, slot)
    assert entries.dtype == torch.long and entries.tolist() == [s for _, s in expected]
    counts = [sum(1 for k in flat if k == p) for p in range(N)]
    assert seg.tolist() == [sum(counts[:p]) for p in range(N + 1)]
    ref_entries, ref_seg = _entries_by_point_sorted(idx, N)  # every slot: the filled ones, then the empty ones
    assert torch.equal(seg, ref_seg) and torch.equal(entries, ref_entries[:int(ref_seg[N])])
    assert ref_entries[int(ref_seg[N]):].tolist() == [s for s, k in enumerate(flat) if k < 0]


def test_backward_point_order_rejects_out_of_range_point():
    from nsplat.ops.build import backend

    idx = torch.tensor([[[[0, 5]]]], dtype=torch.int32)
    with pytest.raises(RuntimeError, match="num_points"):
        backend(torch.device("cpu")).entries_by_point(idx, 3)
