"""Issue 14, op classes 4-7: non-rigid viewmats, validation of the public stages, float32 hazards and
allocation checks. Every bad input raises before native code with a message naming the argument."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from nsplat.ops import Splatter, composite_sample, functional, project, sample, splat, splat_dense
from nsplat.ops.validation import AllocationError, memory_limit
from tests.conftest import make_cameras, make_scene

KW = dict(near=0.01, far=1e10, lowpass=1.0)


def _setup(N: int = 6, B: int = 2, dtype: torch.dtype = torch.float64):
    sc = make_scene(N, 0, dtype=dtype)
    V, K = make_cameras(B, 5, 4, dtype=dtype)
    return sc, V, K


def _args(sc, V, K):
    return (sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K)


# ------------------------------------------------------------------------------- 4. non-rigid viewmats
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sheared_viewmat_is_rejected_naming_viewmats_and_camera(dtype):
    sc, V, K = _setup(dtype=dtype)
    V = V.clone()
    V[1, 0, 1] += 0.3  # shear in camera 1's 3x3 part
    with pytest.raises(ValueError, match=r"^viewmats: camera 1: .*not a rotation"):
        splat(*_args(sc, V, K), 5, 4, samples=2)
    with pytest.raises(ValueError, match=r"^viewmats: camera 1"):
        project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, **KW)


def test_non_uniform_scale_is_rejected_and_uniform_scale_accepted():
    sc, V, K = _setup()
    Vn = V.clone()
    Vn[0, :3, :3] = Vn[0, :3, :3] @ torch.diag(torch.tensor([1.0, 1.0, 1.5], dtype=V.dtype))
    with pytest.raises(ValueError, match=r"^viewmats: camera 0"):
        splat(*_args(sc, Vn, K), 5, 4, samples=2)
    Vu = V.clone()
    Vu[:, :3, :3] *= 2.0  # a rotation times a uniform scale: accepted (documented)
    out = splat(*_args(sc, Vu, K), 5, 4, samples=2)
    assert torch.isfinite(out.image).all()


# ----------------------------------------------------------------------------- 5. the public op stages
def test_project_validates_like_splat():
    sc, V, K = _setup()
    with pytest.raises(ValueError, match=r"^scales: expected shape \[N, 2\]"):
        project(sc["means"], sc["normals"], sc["scales"][:-1], sc["opacities"], V, K, **KW)
    with pytest.raises(ValueError, match=r"^Ks: expected shape \[B, 3, 3\] with B=2"):
        project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K[:1], **KW)
    with pytest.raises(ValueError, match=r"^near"):
        project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=-1.0, far=10.0, lowpass=1.0)


def test_sample_validates_cameras_settings_and_projection():
    sc, V, K = _setup()
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, **KW)
    with pytest.raises(ValueError, match=r"^Ks: expected shape \[B, 3, 3\] with B=2"):
        sample(proj, K[:1], 5, 4)  # camera-count mismatch
    with pytest.raises(ValueError, match=r"^samples: expected an int >= 1, got -3"):
        sample(proj, K, 5, 4, samples=-3)
    with pytest.raises(ValueError, match=r"^width"):
        sample(proj, K, 0, 4)
    bad = dataclasses.replace(proj, amps=proj.amps.clone())
    bad.amps[0, 1] = float("nan")
    with pytest.raises(ValueError, match=r"^proj\.amps: contains NaN"):
        sample(bad, K, 5, 4)
    short = dataclasses.replace(proj, conics=proj.conics[:, :-1])
    with pytest.raises(ValueError, match=r"^proj\.conics: expected shape \[2, 6, 3\]"):
        sample(short, K, 5, 4)


@pytest.mark.parametrize("value", [6, 7, 2**30, 2**31 - 1, -2])
def test_composite_rejects_out_of_range_indices(value):
    sc, V, K = _setup()
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, **KW)
    idx, probs, _, _ = sample(proj, K, 5, 4, samples=3)
    idx = idx.clone()
    idx[1, 2, 3, 0] = value
    probs = probs.clone()
    probs[1, 2, 3, 0] = 0.5
    with pytest.raises(ValueError, match=r"^indices: expected values in \[-1, 6\)"):
        composite_sample(proj, sc["features"], K, idx, probs)


def test_composite_validates_features_cameras_and_probs():
    sc, V, K = _setup()
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, **KW)
    idx, probs, _, _ = sample(proj, K, 5, 4, samples=3)
    with pytest.raises(ValueError, match=r"^features: expected shape \[N, C\] or \[B, N, C\] with N=6, B=2"):
        composite_sample(proj, sc["features"][:4], K, idx, probs)  # too short: would be read out of bounds
    with pytest.raises(ValueError, match=r"^indices: expected shape \[B,H,W,m\] with B=2"):
        composite_sample(proj, sc["features"], K, idx[:1], probs[:1])
    with pytest.raises(ValueError, match=r"^Ks: expected shape \[B, 3, 3\] with B=2"):
        composite_sample(proj, sc["features"], K[:1], idx, probs)
    zero = probs.clone()
    zero[idx >= 0] = 0.0
    with pytest.raises(ValueError, match=r"^probs: expected inclusion probabilities"):
        composite_sample(proj, sc["features"], K, idx, zero)
    with pytest.raises(TypeError, match=r"^indices: expected an int32"):
        composite_sample(proj, sc["features"], K, idx.long(), probs)
    image, _, _ = composite_sample(proj, sc["features"], K, idx, probs)  # the valid call still works
    assert torch.isfinite(image).all()


def test_splatter_fails_at_construction():
    with pytest.raises(ValueError, match=r"^samples"):
        Splatter(samples=0)
    with pytest.raises(ValueError, match=r"^eps"):
        Splatter(eps=0.0)
    with pytest.raises(ValueError, match=r"^composite"):
        Splatter(composite="over")
    with pytest.raises(ValueError, match=r"^far"):
        Splatter(near=1.0, far=0.5)


# ------------------------------------------------------------------------------------ 6. float32 hazards
def _one_splat(s: float, dtype: torch.dtype, grad: bool):
    means = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]], dtype=dtype, requires_grad=grad)
    normals = torch.tensor([[0.0, 0.0, -1.0]] * 2, dtype=dtype)
    scales = torch.tensor([[0.01, 0.01], [s, s]], dtype=dtype, requires_grad=grad)
    op, feat = torch.ones(2, dtype=dtype), torch.ones(2, 3, dtype=dtype)
    V = torch.eye(4, dtype=dtype)[None]
    K = torch.tensor([[100.0, 0, 2], [0, 100.0, 2], [0, 0, 1]], dtype=dtype)[None]
    return means, normals, scales, op, feat, V, K


def test_tiny_float32_splat_without_lowpass_is_refused_when_differentiated():
    args = _one_splat(1e-10, torch.float32, grad=True)  # σ ≈ 1e-8 px: NaN gradients if rendered
    with pytest.raises(ValueError, match=r"^scales: points \[1\] \(camera 0\) .*lowpass=0.*float32"):
        splat(*args, 4, 4, samples=2, lowpass=0.0)
    out = splat(*args, 4, 4, samples=2, lowpass=1e-12)  # the documented remedy: finite gradients
    out.image.sum().backward()
    assert all(torch.isfinite(t.grad).all() for t in (args[0], args[2]))
    with torch.no_grad():  # the forward alone is fine and allowed
        assert torch.isfinite(splat(*args, 4, 4, samples=2, lowpass=0.0).image).all()
    args64 = _one_splat(1e-10, torch.float64, grad=True)
    splat(*args64, 4, 4, samples=2, lowpass=0.0).image.sum().backward()
    assert torch.isfinite(args64[2].grad).all()


def test_huge_float32_splat_is_refused_not_dropped():
    args = _one_splat(1e9, torch.float32, grad=False)  # σ ≈ 1e11 px: det Σ overflows float32
    with pytest.raises(ValueError, match=r"^scales: points \[1\] \(camera 0\) .*too large"):
        splat(*args, 4, 4, samples=2)
    out = splat(*_one_splat(1e9, torch.float64, grad=False), 4, 4, samples=2)  # float64 renders it
    assert float(out.alpha.min()) > 0.5


# ------------------------------------------------------------------------ 7. allocation before validation
@pytest.mark.parametrize("width,height,samples", [(100000, 100000, 40), (4, 4, 10**9), (2**40, 1, 1)])
def test_huge_outputs_are_refused_before_allocating(width, height, samples):
    sc, V, K = _setup()
    with pytest.raises(AllocationError, match=r"^width/height/samples: .*samples=.* GiB \(\d+ bytes\)"):
        splat(*_args(sc, V, K), width, height, samples=samples)


def test_huge_outputs_are_refused_before_the_projection(monkeypatch):
    sc, V, K = _setup()

    def no_projection(*args, **kwargs):
        raise AssertionError("the projection ran before the allocation check")

    monkeypatch.setattr(functional, "project_checked", no_projection)
    for width, height, samples in [(100000, 100000, 40), (4, 4, 10**9)]:
        with pytest.raises(AllocationError, match=r"^width/height/samples: "):
            splat(*_args(sc, V, K), width, height, samples=samples)


@pytest.mark.parametrize("grad", [False, True])
def test_dense_oracle_refuses_a_huge_image_before_allocating(grad):
    sc, V, K = _setup()
    args = list(_args(sc, V, K))
    args[4] = args[4].clone().requires_grad_(grad)
    with pytest.raises(AllocationError, match=r"^width/height: 2 camera\(s\) x 100000x100000 px.* dense oracle"):
        splat_dense(*args, 100000, 100000)
    if grad:  # autograd keeps every pixel-point term: a size the forward alone fits is refused with a hint
        side = math.isqrt(memory_limit(torch.device("cpu")) // 400)  # outputs: 1/4 of the memory; graph: 6.7x
        with pytest.raises(AllocationError, match=r"6 points \(autograd.*torch.no_grad\(\)"):
            splat_dense(*args, side, side)
        with torch.no_grad():
            assert splat_dense(*args, 5, 4).image.shape == (2, 4, 5, 3)


@pytest.mark.parametrize("autocast", [False, True])
def test_tensors_on_an_unsupported_device_are_refused_naming_the_argument(autocast):
    sc, V, K = _setup(dtype=torch.float32)
    args = list(_args(sc, V, K))
    for i, name in [(0, "means"), (4, "features"), (6, "Ks")]:
        bad = list(args)
        bad[i] = bad[i].to("meta")
        with torch.autocast("cpu", enabled=autocast):
            with pytest.raises(ValueError, match=rf"^{name}: expected a tensor on the CPU or a CUDA device, got "
                                                 r"device meta"):
                splat(*bad, 5, 4, samples=2)
            with pytest.raises(ValueError, match=rf"^{name}: expected a tensor on the CPU or a CUDA device"):
                splat_dense(*bad, 5, 4)
    meta = [t.to("meta") for t in args]
    with pytest.raises(ValueError, match=r"^means: expected a tensor on the CPU or a CUDA device"):
        project(*meta[:4], meta[5], meta[6], **KW)
    proj = project(*args[:4], V.float(), K.float(), **KW)
    with pytest.raises(ValueError, match=r"^Ks: expected a tensor on the CPU or a CUDA device"):
        sample(proj, K.float().to("meta"), 5, 4, samples=2)


def test_samples_beyond_int32_are_refused():
    sc, V, K = _setup()
    with pytest.raises(ValueError, match=r"^samples: expected an int in \[1, 2147483647\], got 4294967297"):
        splat(*_args(sc, V, K), 4, 4, samples=2**32 + 1)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, **KW)
    with pytest.raises(ValueError, match=r"^samples"):
        sample(proj, K, 4, 4, samples=2**32 + 1)
