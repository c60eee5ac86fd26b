"""The op as a citizen of other networks (docs/op.md "Using the op in other networks"): the custom ops
(``torch.library``, namespace ``nsplat``) under ``torch.compile(fullgraph=True)``, autocast, the double
backward error and ``torch.library.opcheck``.

The compile tests use ``backend="aot_eager"``: it traces forward and backward with the fake kernels
(Dynamo + AOTAutograd, where graph breaks and wrong fake shapes/strides show) without compiling C++ with
Inductor, which takes minutes on this CPU-only test machine. ``fullgraph=True`` raises on any graph break.
"""
from __future__ import annotations

import pytest
import torch
from torch import nn

from nsplat.ops import Splatter, composite_sample, project, sample, splat
from nsplat.ops.library import composite_backward_op, composite_forward_op, project_backward_op, project_op, sample_op
from tests.conftest import make_cameras, make_scene

PARAMS = ("means", "normals", "scales", "opacities", "features")
W, H = 16, 12


class SplatConvNet(nn.Module):
    """Surfels rendered by :class:`Splatter` ``[B,H,W,C]`` into a conv head ``[B,3,H,W]``."""

    def __init__(self, C: int = 4, **splatter_kw: object) -> None:
        super().__init__()
        sc = make_scene(30, 0, C=C, dtype=torch.float32, spread=0.3)
        self.surfels = nn.ParameterDict({n: nn.Parameter(sc[n]) for n in PARAMS})
        self.splatter = Splatter(samples=4, **splatter_kw)
        self.head = nn.Conv2d(C, 3, 3, padding=1)

    def forward(self, viewmats: torch.Tensor, Ks: torch.Tensor) -> torch.Tensor:
        s = self.surfels
        out = self.splatter(s["means"], s["normals"], s["scales"], s["opacities"], s["features"], viewmats, Ks, W, H)
        return self.head(out.image.permute(0, 3, 1, 2))


def _twins(**kw: object) -> tuple[SplatConvNet, SplatConvNet]:
    torch.manual_seed(0)
    a = SplatConvNet(**kw)
    b = SplatConvNet(**kw)
    b.load_state_dict(a.state_dict())
    return a, b


def _cameras() -> tuple[torch.Tensor, torch.Tensor]:
    return make_cameras(2, W, H, focal=12.0, dtype=torch.float32)


@pytest.mark.parametrize("deterministic", [True, False])
def test_compile_fullgraph_equals_eager(deterministic):
    """``torch.compile(fullgraph=True)`` of Splatter + conv head traces without a graph break and equals
    eager bit for bit, forward and gradients, over two steps (the per-call seed advances as a tensor)."""
    eager, compiled = _twins(deterministic=deterministic)
    run = torch.compile(compiled, fullgraph=True, backend="aot_eager")
    V, K = _cameras()
    for _ in range(2):
        ya, yb = eager(V, K), run(V, K)
        assert torch.equal(ya, yb)
        ga = torch.autograd.grad(ya.square().sum(), list(eager.parameters()))
        gb = torch.autograd.grad(yb.square().sum(), list(compiled.parameters()))
        for (name, _), x, y in zip(eager.named_parameters(), ga, gb):
            if deterministic:
                assert torch.equal(x, y), name
            else:  # atomic-scatter backward: summation order varies between runs
                torch.testing.assert_close(x, y, msg=name)
    assert int(eager.splatter.calls) == int(compiled.splatter.calls) == 2


def test_compile_functional_stages_fullgraph():
    """The functional stages (project → sample → composite_sample) compose in a compiled function."""
    sc = make_scene(12, 0, C=3, dtype=torch.float32, spread=0.3)
    V, K = _cameras()

    def fn(means, normals, scales, opacities, features):
        proj = project(means, normals, scales, opacities, V, K, near=0.01, far=1e10, lowpass=1.0)
        idx, pr, total, work = sample(proj, K, W, H, samples=3, seed=5)
        image, alpha, depth = composite_sample(proj, features, K, idx, pr, composite="additive")
        return image, alpha, depth, total, work

    ref = fn(*(sc[n] for n in PARAMS))
    got = torch.compile(fn, fullgraph=True, backend="aot_eager")(*(sc[n] for n in PARAMS))
    for a, b in zip(got, ref):
        assert a.dtype == b.dtype and torch.equal(a, b)


def test_autocast_bfloat16_runs_op_in_float32():
    """Under ``torch.autocast("cpu", bfloat16)`` the op runs in float32 and returns float32, equal to the
    float32 run; the conv head runs in bfloat16; forward and backward run, gradients match the float32
    run's to bfloat16 precision of the head."""
    plain, mixed = _twins()
    V, K = _cameras()
    s = mixed.surfels
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = mixed.splatter(s["means"], s["normals"], s["scales"], s["opacities"], s["features"], V, K, W, H, seed=3)
        y = mixed.head(out.image.permute(0, 3, 1, 2))
    ref = plain.splatter(*(plain.surfels[n] for n in PARAMS), V, K, W, H, seed=3)
    for name in ("image", "alpha", "depth", "total", "probs"):
        assert getattr(out, name).dtype == torch.float32, name
        assert torch.equal(getattr(out, name), getattr(ref, name)), name
    assert y.dtype == torch.bfloat16
    y.float().square().sum().backward()
    for name in PARAMS:
        g = s[name].grad
        assert g is not None and g.dtype == torch.float32 and bool(torch.isfinite(g).all()), name
    # the op's own backward under autocast equals the float32 backward exactly (same upstream gradient)
    gi = torch.randn(out.image.shape, generator=torch.Generator().manual_seed(0))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out2 = mixed.splatter(*(s[n] for n in PARAMS), V, K, W, H, seed=3)
    got = torch.autograd.grad((out2.image * gi).sum(), [s[n] for n in PARAMS])
    want = torch.autograd.grad((ref.image * gi).sum(), [plain.surfels[n] for n in PARAMS])
    for name, a, b in zip(PARAMS, got, want):
        assert torch.equal(a, b), name


def test_autocast_bfloat16_features_are_cast():
    """bfloat16 features (as a network under autocast produces them) are taken in float32."""
    sc = make_scene(12, 0, C=3, dtype=torch.float32, spread=0.3)
    V, K = _cameras()
    feats = sc["features"].bfloat16()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], feats, V, K, W, H, samples=3)
    ref = splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], feats.float(), V, K, W, H, samples=3)
    assert out.image.dtype == torch.float32 and torch.equal(out.image, ref.image)


def test_bfloat16_outside_autocast_is_still_refused():
    """Outside autocast the dtype rule is unchanged: float32 or float64 only."""
    sc = make_scene(5, 0, C=3, dtype=torch.float32)
    V, K = _cameras()
    with pytest.raises(TypeError, match="features"):
        splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"].bfloat16(), V, K, W, H)


def test_double_backward_raises_naming_the_op():
    """Differentiating the op's gradients raises a clear error naming the op's stage (create_graph alone is fine):
    the native projection's backward or the compositor's, whichever autograd reaches first."""
    sc = make_scene(12, 0, C=3, dtype=torch.float64, spread=0.3)
    V, K = make_cameras(1, W, H, focal=12.0)
    ps = [sc[n].clone().requires_grad_() for n in PARAMS]
    out = splat(*ps, V, K, W, H, samples=3)
    g = torch.autograd.grad(out.image.square().sum(), ps[0], create_graph=True)[0]
    with pytest.raises(RuntimeError, match=r"nsplat::(composite|project)_backward: double backward .* not supported"):
        torch.autograd.grad(g.square().sum(), ps)


def _op_inputs(dtype: torch.dtype = torch.float64):
    sc = make_scene(10, 0, C=2, dtype=dtype, spread=0.3)
    V, K = make_cameras(2, 8, 6, focal=8.0, dtype=dtype)
    proj = project(*(sc[n] for n in PARAMS[:4]), V, K, near=0.01, far=1e10, lowpass=1.0)
    f = [proj.means2d, proj.conics, proj.amps, proj.normals_cam, proj.plane_offsets, proj.depths]
    f = [t.detach().clone() for t in f]
    sig2 = proj.sigma2.detach().clone()
    return f, sig2, K, sc["features"].clone()


def test_opcheck_custom_ops():
    """``torch.library.opcheck``: schemas, fake kernels, autograd registration and the dispatcher agree."""
    (mu, con, amp, nrm, off, zc), sig2, K, feat = _op_inputs()
    seed = torch.tensor(7)
    torch.library.opcheck(sample_op, (mu, con, amp, sig2, nrm, off, zc, K, seed, 8, 6, 3, 0.01, 8, 1e-3, 0, False))
    idx, pr, _, _ = sample_op(mu, con, amp, sig2, nrm, off, zc, K, seed, 8, 6, 3, 0.01, 8, 1e-3, 0, False)
    bg = torch.tensor([0.1, 0.2], dtype=torch.float64)
    params = [t.requires_grad_() for t in (mu, con, amp, nrm, off, zc)]
    args = (*params, K, feat.requires_grad_(), bg.requires_grad_(), idx, pr, 0, 0, True)
    torch.library.opcheck(composite_forward_op, args)
    g = torch.Generator().manual_seed(2)
    gs = [torch.randn(2, 6, 8, c, generator=g, dtype=torch.float64) for c in (2, 1, 1)]
    plain = [t.detach() for t in (*params, K, feat, bg)]
    torch.library.opcheck(composite_backward_op, (*plain, idx, pr, *gs, 0, 0, True),
                          test_utils=("test_schema", "test_faketensor", "test_aot_dispatch_static"))


def test_opcheck_projection_ops():
    """``torch.library.opcheck`` of the native projection and its backward (CPU kernels)."""
    sc = make_scene(10, 0, C=2, spread=0.3)
    V, K = make_cameras(2, 8, 6, focal=8.0)
    args = [sc[n].clone().requires_grad_() for n in PARAMS[:4]] + [V.clone().requires_grad_(),
                                                                   K.clone().requires_grad_()]
    torch.library.opcheck(project_op, (*args, 0.01, 1e10, 1.0, False))
    out = project_op(*(a.detach() for a in args), 0.01, 1e10, 1.0, False)
    g = torch.Generator().manual_seed(3)
    grads = [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in out[:7]]
    torch.library.opcheck(project_backward_op, (*(a.detach() for a in args), 0.01, 1e10, 1.0, False, *grads),
                          test_utils=("test_schema", "test_faketensor", "test_aot_dispatch_static"))
