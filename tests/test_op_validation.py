"""Bad input raises a clear TypeError/ValueError naming the argument, before any native code runs."""
from __future__ import annotations

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import nsplat.ops.library as library
from nsplat.ops import splat, splat_dense
from nsplat.ops.value_checks import fail_if, value_checks
from tests.conftest import make_cameras, make_scene


@pytest.fixture
def no_native(monkeypatch):
    def fail(*_a, **_k):
        raise AssertionError("native code ran before validation")

    monkeypatch.setattr(library, "native", fail)  # every custom op kernel gets its module from here


def _good():
    sc = make_scene(5, 0, dtype=torch.float32)
    V, K = make_cameras(1, 8, 6, dtype=torch.float32)
    return dict(means=sc["means"], normals=sc["normals"], scales=sc["scales"], opacities=sc["opacities"],
                features=sc["features"], viewmats=V, Ks=K, width=8, height=6)


def _nan(t):
    t = t.clone()
    t.view(-1)[0] = float("nan")
    return t


BAD = [
    ("means", lambda a: a["means"][:, :2], ValueError),
    ("normals", lambda a: a["normals"].double(), TypeError),
    ("means", lambda a: a["means"].long(), TypeError),
    ("means", lambda a: a["means"].tolist(), TypeError),
    ("means", lambda a: _nan(a["means"]), ValueError),
    ("normals", lambda a: a["normals"][:4], ValueError),
    ("normals", lambda a: torch.zeros_like(a["normals"]), ValueError),
    ("scales", lambda a: -a["scales"], ValueError),
    ("scales", lambda a: torch.zeros_like(a["scales"]), ValueError),
    ("scales", lambda a: a["scales"][:, :1], ValueError),
    ("opacities", lambda a: a["opacities"] + 2, ValueError),
    ("opacities", lambda a: a["opacities"][:, None], ValueError),
    ("features", lambda a: a["features"][:, :0], ValueError),
    ("features", lambda a: _nan(a["features"]), ValueError),
    ("viewmats", lambda a: a["viewmats"][0], ValueError),
    ("viewmats", lambda a: a["viewmats"] * 2, ValueError),
    ("viewmats", lambda a: float("inf") * a["viewmats"], ValueError),
    ("Ks", lambda a: a["Ks"].repeat(2, 1, 1), ValueError),
    ("Ks", lambda a: -a["Ks"], ValueError),
    ("width", lambda a: 0, ValueError),
    ("width", lambda a: 8.0, TypeError),
    ("height", lambda a: -3, ValueError),
]


@pytest.mark.parametrize("arg,make,exc", BAD)
def test_bad_tensor_arguments(arg, make, exc, no_native):
    args = _good()
    args[arg] = make(args)
    with pytest.raises(exc, match=rf"^{arg}:"):
        splat(**args)


@pytest.mark.parametrize("kw,value,exc", [
    ("samples", 0, ValueError), ("samples", 2.5, TypeError), ("eps", 0.0, ValueError), ("eps", -1.0, ValueError),
    ("eps", 2.0, ValueError), ("estimator", "biased", ValueError), ("composite", "max", ValueError),
    ("near", 0.0, ValueError), ("far", 0.001, ValueError), ("lowpass", -1.0, ValueError), ("seed", -1, ValueError),
    ("hermite_order", 17, ValueError), ("hermite_tol", 0.0, ValueError), ("background", torch.zeros(2), ValueError),
    ("background", torch.zeros(3, dtype=torch.float64), TypeError),
])
def test_bad_settings(kw, value, exc, no_native):
    with pytest.raises(exc, match=rf"^{kw}:"):
        splat(**_good(), **{kw: value})


def test_dense_validates_too():
    args = _good()
    args["scales"] = -args["scales"]
    with pytest.raises(ValueError, match="^scales:"):
        splat_dense(**args)


def test_mixed_devices_are_rejected(no_native):
    args = _good()
    args["features"] = args["features"].to("meta")
    with pytest.raises(ValueError, match="^features:.*device"):
        splat(**args)


# ------------------------------------------------------------------------- value checks in one host read
class _ScalarReads(TorchDispatchMode):
    """Counts the reads of one tensor value back to the host (``bool(t)``, ``t.item()``: on a GPU each one is a
    synchronisation)."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        self.count += func is torch.ops.aten._local_scalar_dense.default
        return func(*args, **(kwargs or {}))


def test_splat_value_checks_read_no_scalar_per_check():
    """splat's data-dependent checks (finite values, ranges, rigid viewmats, per-camera seeds, the projection's
    float hazards) are read back together (ops/value_checks.py), not one scalar per check as before (17 such
    reads in this call); nothing in the forward or the backward reads a scalar."""
    sc = make_scene(300, 1, C=3)
    V, K = make_cameras(2, 16, 12)
    ps = [sc[n].requires_grad_() for n in ("means", "normals", "scales", "opacities", "features")]
    with _ScalarReads() as reads:
        out = splat(*ps, V, K, 16, 12, samples=8, seed=torch.tensor([1, 2]))
        out.image.sum().backward()
    assert reads.count == 0


def test_value_checks_raise_the_first_failure_in_call_order_when_the_block_ends():
    built = []
    reached_end = False
    with pytest.raises(ValueError, match="^first$"):
        with value_checks():
            fail_if(torch.tensor(False), lambda: built.append("passing") or "never")
            fail_if(torch.tensor(True), lambda: "first")
            fail_if(torch.tensor([True]).any(), lambda: "second")
            reached_end = True
    assert reached_end and built == []  # deferred to the end; a passing check's message is never built
    with value_checks():
        fail_if(torch.tensor(False), lambda: "never")
    with pytest.raises(ValueError, match="^now$"):  # outside a block: at once
        fail_if(torch.tensor(True), lambda: "now")


def test_nested_value_checks_join_the_outermost():
    with pytest.raises(ValueError, match="^inner$"):
        with value_checks():
            with value_checks():
                fail_if(torch.tensor(True), lambda: "inner")
            fail_if(torch.tensor(True), lambda: "outer")


def test_several_bad_values_name_the_first_argument(no_native):
    kw = _good()
    kw["means"] = _nan(kw["means"])
    kw["scales"] = -kw["scales"]
    with pytest.raises(ValueError, match="^means: contains NaN or Inf$"):
        splat(**kw, samples=4)
    kw = _good()
    kw["scales"] = -kw["scales"]
    kw["viewmats"] = kw["viewmats"] * torch.tensor([1.0, 2.0, 1.0, 1.0])[:, None]
    with pytest.raises(ValueError, match="^scales: expected values > 0"):
        splat(**kw, samples=4)
