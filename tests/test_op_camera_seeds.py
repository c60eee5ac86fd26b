"""One seed per camera (``seed`` a ``[B]`` tensor): views rendered in one call sample, composite and back-propagate
as the same views rendered one call each, so a training step may batch its views (and split them over ranks)
without changing what it computes; a 0-dim seed keeps independent streams per camera of a call."""
from __future__ import annotations

import pytest
import torch

from nsplat.ops import sample, splat
from nsplat.ops.projection import project
from tests.conftest import make_cameras, make_scene

W, H = 20, 16
SEEDS = (11, 2**62 + 5, 7)


def _leaves(sc: dict[str, torch.Tensor], V: torch.Tensor) -> list[torch.Tensor]:
    return [t.clone().requires_grad_() for t in (sc["means"], sc["normals"], sc["scales"], sc["opacities"],
                                                   sc["features"], V)]


@pytest.mark.parametrize("estimator, composite, stratified", [("ht", "alpha", False), ("sampled", "alpha", True),
                                                              ("paper", "additive", False)])
def test_per_camera_seeds_render_as_one_call_per_view(estimator, composite, stratified):
    sc = make_scene(60, 3, C=4)
    V, K = make_cameras(3, W, H)
    bg = torch.tensor([0.2, 0.4, 0.6, 0.8], dtype=torch.float64)
    g_img = torch.rand(3, H, W, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    leaves = _leaves(sc, V)
    out = splat(*leaves, K, W, H, samples=6, estimator=estimator, composite=composite, background=bg,
                seed=torch.tensor(SEEDS), stratified=stratified)
    grads = torch.autograd.grad((out.image * g_img).sum(), leaves)

    want = [torch.zeros_like(g) for g in grads]
    for b, s in enumerate(SEEDS):
        one = _leaves(sc, V)
        o = splat(*one[:5], one[5][b:b + 1], K[b:b + 1], W, H, samples=6, estimator=estimator, composite=composite,
                  background=bg, seed=s, stratified=stratified)
        for name in ("indices", "probs", "total", "image", "alpha", "depth"):
            assert torch.equal(getattr(out, name)[b:b + 1], getattr(o, name)), (b, name)
        for acc, g in zip(want, torch.autograd.grad((o.image * g_img[b:b + 1]).sum(), one)):
            acc += g
    for name, got, ref in zip(("means", "normals", "scales", "opacities", "features", "viewmats"), grads, want):
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-14, msg=name)  # float64: summation order only


def test_a_scalar_seed_draws_independent_streams_per_camera():
    """Three copies of one camera under one 0-dim seed sample differently; under ``[s, s, s]`` identically."""
    sc = make_scene(60, 3)
    V, K = make_cameras(1, W, H)
    V, K = V.repeat(3, 1, 1), K.repeat(3, 1, 1)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=100.0,
                   lowpass=0.3)
    idx = sample(proj, K, W, H, samples=4, seed=5)[0]
    assert not torch.equal(idx[0], idx[1]) and not torch.equal(idx[1], idx[2])
    same = sample(proj, K, W, H, samples=4, seed=torch.tensor([5, 5, 5]))[0]
    assert torch.equal(same[0], same[1]) and torch.equal(same[1], same[2])
    assert torch.equal(same[0], idx[0])  # camera 0 of a call with seed 5


@pytest.mark.parametrize("seed, error, match", [
    (torch.tensor([1, 2]), ValueError, "one seed per camera expected, got 2 seeds for 3 cameras"),
    (torch.tensor([1, -2, 3]), ValueError, r"seed: expected values in \[0, 2\*\*63\)"),
    (torch.tensor([[1, 2, 3]]), TypeError, "one seed per camera"),
    (torch.tensor([1.0, 2.0, 3.0]), TypeError, "seed: expected an int"),
])
def test_bad_per_camera_seeds_are_refused_naming_seed(seed, error, match):
    sc = make_scene(20, 3)
    V, K = make_cameras(3, W, H)
    with pytest.raises(error, match=match):
        splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, W, H, samples=4,
              seed=seed)
