"""Numerical stability at the extremes: no NaN/Inf in outputs or gradients."""
from __future__ import annotations

import pytest
import torch

from nsplat.ops import splat
from tests.conftest import make_cameras, make_scene


def _run(sc, V, K, W, H, **kw):
    ps = [t.clone().requires_grad_() for t in (sc["means"], sc["normals"], sc["scales"], sc["opacities"],
                                               sc["features"], V)]
    bg = torch.full((sc["features"].shape[1],), 0.5, dtype=V.dtype, requires_grad=True)
    out = splat(*ps, K, W, H, background=bg, **kw)
    for name in ("image", "alpha", "depth", "total", "probs"):
        t = getattr(out, name)
        assert bool(torch.isfinite(t).all()), f"{name} has NaN/Inf"
    assert bool(((out.alpha >= 0) & (out.alpha <= 1)).all()) or kw.get("composite") == "additive"
    loss = out.image.square().sum() + out.alpha.sum() + out.depth.sum()
    grads = torch.autograd.grad(loss, ps + [bg], allow_unused=True)
    for g in grads:
        assert g is None or bool(torch.isfinite(g).all()), "gradient has NaN/Inf"
    return out


def _scene(N=20, seed=0, dtype=torch.float32, **kw):
    return make_scene(N, seed, dtype=dtype, **kw)


CASES = {
    "tiny_scales": lambda sc: sc["scales"].fill_(1e-6),
    "huge_scales": lambda sc: sc["scales"].fill_(1e3),
    "edge_on_exact": lambda sc: sc["normals"].copy_(torch.tensor([1.0, 0.0, 0.0]).expand_as(sc["normals"])),
    "edge_on_nearly": lambda sc: sc["normals"].copy_(torch.tensor([1.0, 0.0, 1e-6]).expand_as(sc["normals"])),
    "behind_camera": lambda sc: sc["means"][:, 2].fill_(-10.0),
    "at_near_plane": lambda sc: sc["means"][:, 2].fill_(-2.5 + 0.01),
    "coincident": lambda sc: (sc["means"].copy_(sc["means"][:1].expand_as(sc["means"])),
                              sc["normals"].copy_(sc["normals"][:1].expand_as(sc["normals"])),
                              sc["scales"].copy_(sc["scales"][:1].expand_as(sc["scales"]))),
    "far_coordinates": lambda sc: sc["means"].add_(1e4),
    "huge_opacity": lambda sc: sc["opacities"].fill_(1.0),
    "zero_opacity": lambda sc: sc["opacities"].fill_(0.0),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("composite,estimator", [("alpha", "ht"), ("additive", "paper"), ("alpha", "sampled")])
def test_extreme_scenes_are_finite(case, composite, estimator):
    sc = _scene()
    CASES[case](sc)
    V, K = make_cameras(2, 16, 12, dtype=torch.float32)
    _run(sc, V, K, 16, 12, samples=8, composite=composite, estimator=estimator)


@pytest.mark.parametrize("N", [0, 1, 3])
def test_few_points_and_fewer_than_samples(N):
    sc = _scene(N=N)
    V, K = make_cameras(2, 9, 7, dtype=torch.float32)
    out = _run(sc, V, K, 9, 7, samples=5)
    assert out.indices.shape == (2, 7, 9, 5)
    assert bool((out.indices[..., N:] == -1).all())


@pytest.mark.parametrize("W,H", [(1, 1), (1, 17), (23, 2), (40, 9)])
def test_odd_image_sizes(W, H):
    sc = _scene(N=30)
    V, K = make_cameras(1, W, H, dtype=torch.float32, focal=20.0)
    out = _run(sc, V, K, W, H, samples=4)
    assert out.image.shape == (1, H, W, 3)


def test_pixels_far_from_every_point_show_background():
    sc = _scene(N=10, scale=(0.001, 0.002))
    sc["means"][:, :2] = 0.0
    V, K = make_cameras(1, 200, 3, dtype=torch.float32, focal=60.0)
    out = _run(sc, V, K, 200, 3, samples=4)
    assert torch.allclose(out.image[0, :, -20:], torch.full_like(out.image[0, :, -20:], 0.5))


def test_many_samples_and_channels():
    sc = _scene(N=50, C=33)
    V, K = make_cameras(3, 8, 8, dtype=torch.float32)
    out = _run(sc, V, K, 8, 8, samples=200)
    assert out.image.shape == (3, 8, 8, 33)


@pytest.mark.parametrize("big", [1e20, 1e30])
def test_culled_points_with_huge_coordinates_or_scales_leave_gradients_finite(big):
    """Points outside [near, far] with float32-overflowing lateral coordinates or scales change nothing:
    the image equals the scene without them and every gradient (cameras' included) stays finite."""
    torch.manual_seed(0)
    N = 12
    means = torch.randn(N, 3) * 0.3
    means[:, 2] += 3.0
    normals = torch.tensor([0.0, 0.0, -1.0]).expand(N, 3).clone()
    scales = torch.full((N, 2), 0.1)
    opac, feats = torch.full((N,), 0.8), torch.rand(N, 3)
    extra_means = torch.tensor([[big, -big, -5.0], [0.1, 0.2, -3.0]])   # behind the camera
    extra_scales = torch.tensor([[0.1, 0.1], [big, big]])
    K = torch.tensor([[[30.0, 0.0, 16.0], [0.0, 30.0, 16.0], [0.0, 0.0, 1.0]]])

    def run(with_extra: bool):
        m = torch.cat([means, extra_means]) if with_extra else means
        s = torch.cat([scales, extra_scales]) if with_extra else scales
        n = torch.cat([normals, normals[:2]]) if with_extra else normals
        o = torch.cat([opac, opac[:2]]) if with_extra else opac
        f = torch.cat([feats, feats[:2]]) if with_extra else feats
        ps = [t.clone().requires_grad_() for t in (m, n, s, o, f)]
        V = torch.eye(4)[None].clone().requires_grad_()
        out = splat(*ps, V, K, 32, 32, samples=8, seed=3)
        out.image.sum().backward()
        return out.image.detach(), [p.grad for p in ps], V.grad

    img, grads, gV = run(True)
    ref, ref_grads, ref_gV = run(False)
    assert all(torch.isfinite(g).all() for g in grads) and torch.isfinite(gV).all()
    torch.testing.assert_close(img, ref, rtol=0, atol=1e-6)
    assert torch.count_nonzero(grads[0][N:]) == 0 and torch.count_nonzero(grads[2][N:]) == 0
    torch.testing.assert_close(gV, ref_gV, rtol=1e-5, atol=1e-5)
