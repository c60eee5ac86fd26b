"""The native CPU projection (``nsplat::project``) against its pure-PyTorch reference ``project_torch``:
forward values, the hand-derived backward against autograd and finite differences, every branch (culled by
near/far, back faces, isotropic splats), and bitwise determinism across thread counts."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from nsplat.ops import project
from nsplat.ops.library import project_op
from nsplat.ops.projection import project_torch

from .conftest import make_cameras, make_scene

FIELDS = ("means2d", "conics", "amps", "normals_cam", "plane_offsets", "depths", "sigma2")


def _inputs(dtype: torch.dtype, N: int = 300, B: int = 3, seed: int = 0) -> dict:
    sc = make_scene(N, seed, dtype=dtype)
    V, K = make_cameras(B, 64, 48, dtype=dtype)
    # some points behind the near plane or beyond far, some facing away (for back-face culling)
    sc["means"][:10, 2] = -3.0
    sc["means"][10:20, 2] = 40.0
    sc["normals"][20:60, 2] *= -1.0
    return dict(means=sc["means"], normals=sc["normals"], scales=sc["scales"], opacities=sc["opacities"],
                viewmats=V, Ks=K)


def _project(fn, x: dict, **kw):  # noqa: ANN001
    return fn(x["means"], x["normals"], x["scales"], x["opacities"], x["viewmats"], x["Ks"], near=0.5, far=30.0,
              lowpass=kw.pop("lowpass", 0.3), **kw)


@pytest.mark.parametrize("cull", [False, True])
@pytest.mark.parametrize("dtype,rtol,atol", [(torch.float64, 1e-12, 1e-12), (torch.float32, 2e-5, 1e-5)])
def test_forward_equals_reference(cull, dtype, rtol, atol):
    x = _inputs(dtype)
    a, b = _project(project, x, backface_cull=cull), _project(project_torch, x, backface_cull=cull)
    assert torch.equal(a.valid, b.valid)
    assert 0 < int(a.valid.sum()) < a.valid.numel()  # both branches are exercised
    for f in FIELDS:
        torch.testing.assert_close(getattr(a, f), getattr(b, f), rtol=rtol, atol=atol, msg=f)


@pytest.mark.parametrize("cull", [False, True])
def test_backward_equals_autograd_of_reference(cull):
    """Every input's gradient for a random linear function of every output, float64."""
    x = _inputs(torch.float64)
    g = torch.Generator().manual_seed(1)
    ref = _project(project_torch, x, backface_cull=cull)
    weights = {f: torch.randn(getattr(ref, f).shape, generator=g, dtype=torch.float64) for f in FIELDS}
    grads = []
    for fn in (project, project_torch):
        leaves = {k: v.clone().requires_grad_(True) for k, v in x.items()}
        out = _project(fn, leaves, backface_cull=cull)
        loss = sum((getattr(out, f) * w).sum() for f, w in weights.items())
        grads.append(torch.autograd.grad(loss, list(leaves.values())))
    for name, a, b in zip(x, *grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10, msg=name)


def test_backward_of_unused_outputs_is_zero_and_matches():
    """Only ``amps`` in the loss: the other outputs' gradients enter as zeros."""
    x = _inputs(torch.float64, N=80, B=2)
    grads = []
    for fn in (project, project_torch):
        leaves = {k: v.clone().requires_grad_(True) for k, v in x.items()}
        grads.append(torch.autograd.grad(_project(fn, leaves).amps.sum(), list(leaves.values())))
    for name, a, b in zip(x, *grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12, msg=name)


def test_gradcheck_native():
    """Finite differences of the native op itself (float64), every differentiable output."""
    x = _inputs(torch.float64, N=12, B=2, seed=3)
    x["scales"] = x["scales"] * torch.tensor([1.0, 1.7], dtype=torch.float64)  # anisotropic: sigma2 smooth

    def f(*args):  # noqa: ANN002
        return project_op(*args, 0.5, 30.0, 0.3, False)[:7]

    args = [v.clone().requires_grad_(True) for v in x.values()]
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_isotropic_splat_sigma2_gradient_is_finite():
    """An isotropic splat (the discriminant of sigma2 is exactly 0): the native gradient stays finite."""
    means = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    normals = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    scales = torch.tensor([[0.1, 0.1]], dtype=torch.float64, requires_grad=True)
    op = torch.tensor([0.5], dtype=torch.float64)
    V, K = make_cameras(1, 32, 32)
    out = project(means, normals, scales, op, V, K, near=0.1, far=10.0, lowpass=0.3)
    gm, gs = torch.autograd.grad(out.sigma2.sum() + out.amps.sum(), [means, scales])
    assert torch.isfinite(gm).all() and torch.isfinite(gs).all()


def test_bitwise_across_thread_counts():
    x = _inputs(torch.float32, N=3000, B=3)
    results = []
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            leaves = {k: v.clone().requires_grad_(True) for k, v in x.items()}
            out = _project(project, leaves)
            loss = sum(getattr(out, f).square().sum() for f in FIELDS)
            results.append([*(getattr(out, f) for f in FIELDS),
                            *torch.autograd.grad(loss, list(leaves.values()))])
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_native_hazards_raise_like_the_reference():
    """A splat too large for float32 is refused by name by both paths."""
    x = _inputs(torch.float32, N=100, B=1)
    x["scales"] = x["scales"].clone()
    x["scales"][70] = 1e30
    for fn in (project, project_torch):
        with pytest.raises(ValueError, match=r"scales: points \[70\]"):
            _project(fn, x)


def test_projected_is_a_plain_dataclass_of_the_native_outputs():
    x = _inputs(torch.float32, N=10, B=1)
    out = _project(project, x)
    assert [f.name for f in dataclasses.fields(out)] == [*FIELDS, "valid"]
    assert out.valid.dtype == torch.bool
