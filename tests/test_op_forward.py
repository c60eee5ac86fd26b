"""Forward pass of the sampled op against the dense oracle."""
from __future__ import annotations

import pytest
import torch

from nsplat.ops import Splatter, splat, splat_dense
from tests.conftest import make_cameras, make_scene

W, H = 20, 16


def _args(sc, V, K):
    return (sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, W, H)


@pytest.mark.parametrize("composite", ["alpha", "additive"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_full_sample_equals_dense(composite, dtype):
    """With samples >= N every point is sampled (π = 1) and the op equals the dense renderer."""
    sc = make_scene(40, 1, C=5, dtype=dtype)
    V, K = make_cameras(3, W, H, dtype=dtype)
    bg = torch.linspace(0.1, 0.9, 5, dtype=dtype)
    out = splat(*_args(sc, V, K), samples=40, composite=composite, background=bg)
    ref = splat_dense(*_args(sc, V, K), composite=composite, background=bg)
    for name in ("image", "alpha", "depth", "total"):
        a, b = getattr(out, name), getattr(ref, name)
        assert a.shape == b.shape
        scale = max(1.0, float(b.abs().max()))
        assert torch.allclose(a, b, atol=1e-5 * scale, rtol=0), (name, float((a - b).abs().max()))
    assert bool((out.probs[out.indices >= 0] == 1).all())


def test_error_shrinks_as_samples_grow():
    """Alpha compositing of a sample misses points; the mean error to the dense image falls with m."""
    sc = make_scene(300, 2, dtype=torch.float32, scale=(0.05, 0.2))
    V, K = make_cameras(1, W, H, dtype=torch.float32)
    ref = splat_dense(*_args(sc, V, K)).image
    errors = []
    for m in (1, 4, 16, 64):
        e = [float((splat(*_args(sc, V, K), samples=m, seed=s).image - ref).abs().mean()) for s in range(3)]
        errors.append(sum(e) / len(e))
    assert all(a > b for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 0.25 * errors[0], errors


@pytest.mark.parametrize("estimator", ["ht", "ht-pips"])
def test_additive_forward_mean_vs_dense(estimator):
    """Additive mode is a Horvitz–Thompson sum. With the threshold weights ("ht") its mean over 4000 draws
    equals the dense image (exactly unbiased): every pixel and channel within the family-wise bound of
    360 t-statistics, mean z² ≈ 1. With the πps weights ("ht-pips") the same comparison detects the bias
    (SPS meets the πps targets only approximately, and the certainty units are solved per sample)."""
    w, h, m, R = 12, 10, 4, 40
    sc = make_scene(16, 3, dtype=torch.float64, spread=0.3)
    V, K = make_cameras(1, w, h, dtype=torch.float64)
    args = (sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"])
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    dense = splat_dense(*args, V, K, w, h, composite="additive", background=bg).image[0].reshape(-1, 3)
    # batch means: each call renders `per` copies of the camera (independent streams), R group means
    per = 100
    Vb, Kb = V.expand(per, 4, 4).contiguous(), K.expand(per, 3, 3).contiguous()
    outs = torch.stack([splat(*args, Vb, Kb, w, h, samples=m, composite="additive", eps=1e-6, seed=s,
                              background=bg, estimator=estimator).image.mean(0) for s in range(R)]).reshape(R, -1, 3)
    mean, se = outs.mean(0), outs.std(0) / R ** 0.5
    z = (mean - dense) / (se + 1e-300)
    zmax, z2 = float(z.abs().max()), float((z ** 2).mean())
    if estimator == "ht":
        assert zmax <= 5.0 and z2 <= 1.5, (zmax, z2)  # family-wise ~0.5 % for 360 t(39) statistics
    else:
        assert zmax > 8.0 and z2 > 2.0, (zmax, z2)


def test_module_wrapper_and_any_channel_count():
    sc = make_scene(30, 4, C=7, dtype=torch.float32)
    V, K = make_cameras(2, W, H, dtype=torch.float32)
    mod = Splatter(samples=8, eps=0.01)
    a = mod(sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, W, H)
    b = mod(sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, W, H)
    assert a.image.shape == (2, H, W, 7)
    assert not torch.equal(a.indices, b.indices), "the module advances its seed every call"
    c = mod(sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, W, H, seed=5)
    d = splat(*_args(sc, V, K)[:7], W, H, samples=8, eps=0.01, seed=5)
    assert torch.equal(c.image, d.image)
    assert "samples=8" in repr(mod)


@pytest.mark.parametrize("renderer", ["splat", "dense", "truncated"])
def test_backface_cull_renders_exactly_the_surfels_facing_each_camera(renderer):
    """``backface_cull=True`` equals rendering, per camera, only the surfels whose normal faces it (n_c·q < 0)
    with the same renderer (the sampled op with m >= N is exact); culled surfels get no gradient from that
    camera, and two-sided rendering (the default) differs."""
    from nsplat.render.truncated import splat_truncated
    fn = {"splat": lambda *a, **k: splat(*a, samples=40, **k), "dense": splat_dense,
          "truncated": splat_truncated}[renderer]
    sc = make_scene(40, 1, C=3, dtype=torch.float64)
    sc["normals"][::2] *= -1  # half of them face away from the cameras
    V, K = make_cameras(2, W, H, dtype=torch.float64)
    means = sc["means"].clone().requires_grad_(True)
    out = fn(means, *_args(sc, V, K)[1:], backface_cull=True)
    for b in range(2):
        q = sc["means"] @ V[b, :3, :3].T + V[b, :3, 3]
        front = ((sc["normals"] @ V[b, :3, :3].T) * q).sum(-1) < 0
        assert 0 < int(front.sum()) < 40
        sub = {k: v[front] for k, v in sc.items()}
        ref = fn(*_args(sub, V[b:b + 1], K[b:b + 1]))
        assert torch.allclose(out.image[b:b + 1], ref.image, atol=1e-9, rtol=0), renderer
        grad, = torch.autograd.grad(out.image[b].sum(), means, retain_graph=True)
        assert float(grad[~front].abs().max()) == 0 and float(grad[front].abs().max()) > 0
    two_sided = fn(*_args(sc, V, K))
    assert float((two_sided.image - out.image).detach().abs().max()) > 1e-3


def test_backface_cull_must_be_a_bool():
    sc = make_scene(8, 1, dtype=torch.float32)
    V, K = make_cameras(1, W, H, dtype=torch.float32)
    with pytest.raises(TypeError, match="backface_cull"):
        splat(*_args(sc, V, K), backface_cull=1)
    with pytest.raises(TypeError, match="backface_cull"):
        Splatter(backface_cull="yes")
