"""Per-camera features (``features [B,N,C]``: camera ``b`` sees ``features[b]``, e.g. each view's SH colour): views
rendered in one call composite and back-propagate as the same views rendered one call each with their own
features, so a training step with view-dependent colour may batch its views; the dense oracle agrees, and ``[N,C]``
features behave as the same features given to every camera."""
from __future__ import annotations

import pytest
import torch

from nsplat.ops import splat, splat_dense
from tests.conftest import make_cameras, make_scene

W, H = 20, 16
SEEDS = (11, 2**62 + 5, 7)
GEOMETRY = ("means", "normals", "scales", "opacities")


def _per_camera_features(N: int, B: int, C: int) -> torch.Tensor:
    return torch.rand(B, N, C, generator=torch.Generator().manual_seed(4), dtype=torch.float64)


@pytest.mark.parametrize("deterministic", [True, False])
@pytest.mark.parametrize("estimator, composite", [("ht", "alpha"), ("sampled", "alpha"), ("paper", "additive")])
def test_per_camera_features_render_as_one_call_per_view(estimator, composite, deterministic):
    sc = make_scene(60, 3, C=4)
    V, K = make_cameras(3, W, H)
    feats = _per_camera_features(60, 3, 4)
    bg = torch.tensor([0.2, 0.4, 0.6, 0.8], dtype=torch.float64)
    g_img = torch.rand(3, H, W, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    kw = dict(samples=6, estimator=estimator, composite=composite, background=bg, deterministic=deterministic)

    geo = [sc[n].clone().requires_grad_() for n in GEOMETRY]
    f = feats.clone().requires_grad_()
    out = splat(*geo, f, V, K, W, H, seed=torch.tensor(SEEDS), **kw)
    grads = torch.autograd.grad((out.image * g_img).sum(), [*geo, f])

    want = [torch.zeros_like(g) for g in grads[:4]]
    for b, s in enumerate(SEEDS):
        one = [sc[n].clone().requires_grad_() for n in GEOMETRY]
        fb = feats[b].clone().requires_grad_()
        o = splat(*one, fb, V[b:b + 1], K[b:b + 1], W, H, seed=s, **kw)
        for name in ("indices", "probs", "image", "alpha", "depth"):
            assert torch.equal(getattr(out, name)[b:b + 1], getattr(o, name)), (b, name)
        *g_geo, g_f = torch.autograd.grad((o.image * g_img[b:b + 1]).sum(), [*one, fb])
        if deterministic:  # camera b's segment of each point: the same slots in the same order
            assert torch.equal(grads[4][b], g_f), b
        else:  # atomic scatter: the order of a point's slots varies
            torch.testing.assert_close(grads[4][b], g_f, rtol=1e-12, atol=1e-14)
        for acc, g in zip(want, g_geo):
            acc += g
    for name, got, ref in zip(GEOMETRY, grads, want):
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-14, msg=name)  # float64: summation order only


def test_shared_features_are_per_camera_features_repeated():
    """``[N,C]`` features give the images of the same features repeated per camera, and their gradient is the sum
    of the per-camera gradients."""
    sc = make_scene(50, 2, C=3)
    V, K = make_cameras(3, W, H)
    g_img = torch.rand(3, H, W, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    shared = sc["features"].clone().requires_grad_()
    rep = sc["features"].expand(3, -1, -1).clone().requires_grad_()
    a = splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], shared, V, K, W, H, samples=5, seed=3)
    b = splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], rep, V, K, W, H, samples=5, seed=3)
    assert torch.equal(a.image, b.image)
    (ga,) = torch.autograd.grad((a.image * g_img).sum(), [shared])
    (gb,) = torch.autograd.grad((b.image * g_img).sum(), [rep])
    torch.testing.assert_close(ga, gb.sum(0), rtol=1e-12, atol=1e-14)


def test_dense_oracle_takes_per_camera_features():
    sc = make_scene(30, 1, C=2)
    V, K = make_cameras(2, 12, 10)
    feats = _per_camera_features(30, 2, 2)
    both = splat_dense(sc["means"], sc["normals"], sc["scales"], sc["opacities"], feats, V, K, 12, 10)
    for b in range(2):
        one = splat_dense(sc["means"], sc["normals"], sc["scales"], sc["opacities"], feats[b], V[b:b + 1],
                          K[b:b + 1], 12, 10)
        torch.testing.assert_close(both.image[b:b + 1], one.image, rtol=0, atol=0)


@pytest.mark.parametrize("shape", [(2, 30, 3), (3, 31, 3), (30, 3, 1, 1)])
def test_features_of_the_wrong_shape_are_refused_by_name(shape):
    sc = make_scene(30, 1)
    V, K = make_cameras(3, 12, 10)
    with pytest.raises(ValueError, match=r"features: expected shape \[N, C\] or \[B, N, C\] with N=30, B=3"):
        splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], torch.zeros(shape, dtype=torch.float64),
              V, K, 12, 10)
