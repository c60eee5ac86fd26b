"""Bad input raises a clear TypeError/ValueError naming the argument, before any native code runs."""
from __future__ import annotations

import pytest
import torch

import nsplat.ops.library as library
from nsplat.ops import splat, splat_dense
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
