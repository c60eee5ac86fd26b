"""The native CPU view-dependent colour (``nsplat::view_colour``) against its pure-PyTorch reference
``view_colour_torch``: values and gradients (features, means, viewmat) for every degree, the clamp at 0,
finite differences of the kernel, and bitwise determinism across thread counts."""
from __future__ import annotations

import pytest
import torch

from nsplat.ops.library import view_colour_op
from nsplat.render.sh import view_channels, view_colour, view_colour_torch

from .conftest import make_cameras


def _inputs(degree: int, dtype: torch.dtype = torch.float64, N: int = 400, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    features = torch.randn(N, view_channels(degree), generator=g, dtype=dtype) * 0.4
    features[:, :3] += 0.3  # some colours clamp at 0, most do not
    means = (torch.rand(N, 3, generator=g, dtype=dtype) - 0.5)
    V, _ = make_cameras(3, 32, 32, dtype=dtype)
    return features, means, V[2]


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_forward_and_gradients_equal_reference(degree):
    f, m, V = _inputs(degree)
    w = torch.randn(f.shape[0], 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    outs, grads = [], []
    for fn in (view_colour, view_colour_torch):
        leaves = [t.clone().requires_grad_(True) for t in (f, m, V)]
        out = fn(*leaves)
        outs.append(out)
        grads.append(torch.autograd.grad((out * w).sum(), leaves))
    assert 0 < int((outs[1] == 0).sum()) < outs[1].numel()  # the clamp is exercised
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-12, atol=1e-12)
    for name, a, b in zip(("features", "means", "viewmat"), *grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-11, msg=name)


def test_float32_close_to_reference():
    f, m, V = _inputs(3, torch.float32)
    torch.testing.assert_close(view_colour(f, m, V), view_colour_torch(f, m, V), rtol=1e-5, atol=1e-6)


def test_gradcheck_native():
    f, m, V = _inputs(3, N=6, seed=2)
    f[:, :3] += 2.0  # away from the clamp's kink
    args = [t.clone().requires_grad_(True) for t in (f, m, V)]
    assert torch.autograd.gradcheck(lambda a, b, c: view_colour_op(a, b, c, 3), args, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_bitwise_across_thread_counts():
    f, m, V = _inputs(3, torch.float32, N=5000)
    results = []
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            leaves = [t.clone().requires_grad_(True) for t in (f, m, V)]
            out = view_colour(*leaves)
            results.append([out, *torch.autograd.grad(out.square().sum(), leaves)])
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_opcheck():
    f, m, V = _inputs(2, N=8)
    torch.library.opcheck(view_colour_op, (f.requires_grad_(), m.requires_grad_(), V.requires_grad_(), 2))


def test_degree_zero_and_bad_channels_take_the_reference_path():
    f, m, V = _inputs(0)
    assert torch.equal(view_colour(f, m, V), f.clamp_min(0.0))
    with pytest.raises(ValueError, match="features"):
        view_colour(torch.zeros(f.shape[0], 10, dtype=f.dtype), m, V)
