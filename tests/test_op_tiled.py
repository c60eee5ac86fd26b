"""The tiled renderer (every splat within ``tol`` of its peak) against the dense oracle and its PyTorch twin."""
from __future__ import annotations

import pytest
import torch

from nsplat.ops import project, splat_dense, splat_tiled
from nsplat.ops.tiled import cutoff2_of, point_weights_tiled, splat_tiled_torch
from tests.conftest import make_cameras, make_scene

W, H = 23, 17


def _scene(dtype: torch.dtype, per_camera: bool) -> tuple[tuple, torch.Tensor]:
    sc = make_scene(60, 4, C=4, dtype=dtype, scale=(0.03, 0.2))
    V, K = make_cameras(3, W, H, dtype=dtype)
    feats = sc["features"]
    if per_camera:
        feats = torch.stack([feats * (0.5 + 0.25 * b) for b in range(3)])
    bg = torch.tensor([0.2, 0.4, 0.6, 0.8], dtype=dtype)
    return (sc["means"], sc["normals"], sc["scales"], sc["opacities"], feats, V, K, W, H), bg


@pytest.mark.parametrize("per_camera", [False, True])
@pytest.mark.parametrize("backface_cull", [False, True])
def test_tiled_equals_dense_when_nothing_is_cut(per_camera, backface_cull):
    """At tol = 1e-300 no kernel is cut within float64 range: the image, alpha and depth are the dense
    oracle's to rounding (same depth order, same compositing)."""
    args, bg = _scene(torch.float64, per_camera)
    out = splat_tiled(*args, tol=1e-300, background=bg, backface_cull=backface_cull, lowpass=0.5)
    ref = splat_dense(*args, background=bg, backface_cull=backface_cull, lowpass=0.5)
    for name in ("image", "alpha", "depth"):
        a, b = getattr(out, name), getattr(ref, name)
        assert a.shape == b.shape
        assert float((a - b).abs().max()) < 1e-12 * max(1.0, float(b.abs().max())), name


def test_tiled_error_is_bounded_by_the_cut_tails():
    """At tol the image moves by at most the cut tails: each splat's alpha by <= tol (amplitude <= 1), and the
    alpha-composited image is 1-Lipschitz in each alpha per unit of |feature - what lies behind| <= 2 max|f|.
    So |tiled - dense| <= 2 N tol max(|f|, |bg|); a large tol must show a cut (the bound is not vacuous)."""
    args, bg = _scene(torch.float64, False)
    ref = splat_dense(*args, background=bg)
    scale = max(float(args[4].abs().max()), float(bg.abs().max()))
    for tol in (1e-7, 1e-3):
        err = float((splat_tiled(*args, tol=tol, background=bg).image - ref.image).abs().max())
        assert err <= 2 * 60 * tol * scale, (tol, err)
    assert float((splat_tiled(*args, tol=0.3, background=bg).image - ref.image).abs().max()) > 1e-3


def test_tiled_float32_matches_dense_float32():
    """In float32 the tiled render of the GT setting (tol 1e-7) is the dense oracle's to float rounding."""
    args, bg = _scene(torch.float32, True)
    out = splat_tiled(*args, background=bg).image
    ref = splat_dense(*args, background=bg).image
    assert float((out - ref).abs().max()) < 2e-6


@pytest.mark.parametrize("per_camera", [False, True])
def test_native_matches_torch_twin(per_camera):
    """The CPU kernel and the PyTorch model other devices run agree (float64, same cut)."""
    args, bg = _scene(torch.float64, per_camera)
    means, normals, scales, opac, feats, V, K, w, h = args
    tol = 1e-5
    native = splat_tiled(*args, tol=tol, background=bg)
    proj = project(means, normals, scales, opac, V, K, near=0.01, far=1e10, lowpass=1.0)
    twin = splat_tiled_torch(proj, feats, K, w, h, cutoff2=cutoff2_of(tol), background=bg)
    for name in ("image", "alpha", "depth"):
        assert float((getattr(native, name) - getattr(twin, name)).abs().max()) < 1e-12, name


@pytest.mark.parametrize("tol", [0.0, 1.0, -1e-3, float("nan"), "small"])
def test_bad_tolerance_is_named(tol):
    args, _ = _scene(torch.float32, False)
    with pytest.raises(ValueError, match="tol"):
        splat_tiled(*args, tol=tol)


def test_bad_geometry_is_named_before_native_code():
    args, _ = _scene(torch.float32, False)
    bad = list(args)
    bad[2] = -bad[2]
    with pytest.raises(ValueError, match="scales"):
        splat_tiled(*bad)


def test_point_weights_are_the_dense_compositing_weights():
    """``point_weights_tiled`` is each splat's Σ_x α_k T_k per camera: the dense oracle's gradient of the summed image
    with respect to a unit feature probe (∂I(x)/∂f_k = w_k(x)), to rounding when nothing is cut."""
    args, _ = _scene(torch.float64, False)
    means, normals, scales, opac, _, V, K, w, h = args
    weights = point_weights_tiled(means, normals, scales, opac, V, K, w, h, tol=1e-300)
    assert weights.shape == (3, 60)
    for b in range(3):
        probe = torch.ones(60, 1, dtype=torch.float64, requires_grad=True)
        img = splat_dense(means, normals, scales, opac, probe, V[b:b + 1], K[b:b + 1], w, h).image
        (grad,) = torch.autograd.grad(img.sum(), probe)
        assert float((weights[b] - grad[:, 0]).abs().max()) < 1e-10
