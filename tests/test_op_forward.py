"""Forward pass of the sampled op against the dense oracle."""
from __future__ import annotations

import pytest
import torch

from nsplat.ops import Splatter, project, splat, splat_dense
from nsplat.ops.reference import size_measures, sps_expectation_weights
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


def test_additive_forward_mean_matches_exact_sps_expectation():
    """Additive mode is a Horvitz–Thompson sum: its mean over seeds equals its exact expectation under SPS
    (computed from exact inclusion probabilities) within 4 standard errors, for every pixel and channel."""
    w, h, m, R = 12, 10, 4, 300
    sc = make_scene(16, 3, dtype=torch.float64, spread=0.3)
    V, K = make_cameras(1, w, h, dtype=torch.float64)
    args = (sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, w, h)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    proj = project(*args[:4], V, K, near=0.01, far=1e10, lowpass=1.0)
    lam = size_measures(proj, 0, w, h)
    ratio = sps_expectation_weights(lam, m)
    expected = bg + (ratio * lam) @ sc["features"] - (ratio * lam).sum(1, keepdim=True) * bg
    outs = torch.stack([splat(*args, samples=m, composite="additive", eps=1e-4, seed=s, background=bg).image[0]
                        for s in range(R)]).reshape(R, -1, 3)
    mean, se = outs.mean(0), outs.std(0) / R ** 0.5
    assert torch.all((mean - expected).abs() <= 4 * se + 1e-12), float(((mean - expected).abs() / se).max())
    dense = splat_dense(*args, composite="additive", background=bg).image[0].reshape(-1, 3)
    assert torch.allclose(expected, dense, atol=0.05), "SPS-vs-πps gap larger than expected on this scene"


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
