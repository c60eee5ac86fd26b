"""The CUDA backend against the CPU backend and the dense oracle (run on a machine with a CUDA device).

Every GPU test skips with the reason "no CUDA device" when ``torch.cuda.is_available()`` is false. The
``emulated`` tests run everywhere: they build ``splat_cuda.cu`` and ``projection_cuda.cu`` in their host emulation
mode (``emulate.cpp``: kernels executed sequentially on the CPU, cub replaced by std algorithms) and check their
launch code against the CPU backend; they cannot show anything about device code generation or the GPU memory
model, which only the GPU tests do.

The contract between the backends (docs/op.md §4): both draw the same SPS law from the same counter-based
uniforms, but their searches differ (the CPU walks a tile's items once for its 16 pixels, vector lane per
pixel; CUDA searches each pixel on its own), so their samples agree except on the few pixels where an
eps-event happens in one of them (assert_same_sample_law), and their work counts differ. Given the same sample,
compositing and its backward run the same core code: on the emulated backend bit for bit, on a GPU within
tolerances derived from a float error analysis of the two differences, nvcc's FMA contraction and CUDA's exp
(tests/float_parity.py), evaluated on each test's data, relative to the largest magnitude of the CPU tensor
(``max|a - b| <= tol * max|b|``).

To isolate the native backends, the parity tests feed both devices bit-identical projected inputs (the
PyTorch projection on each device is not part of the comparison); the end-to-end test runs the projection on
each device in float64.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

import nsplat.ops.library as library
from nsplat.ops import composite_sample, project, sample, splat, splat_dense
from nsplat.ops.build import CSRC, build_dir, cxx_standard, source_hash
from nsplat.ops.reference import MIN_TOTAL, size_measures, sps_bruteforce
from nsplat.ops.rng import stratified_uniforms
from nsplat.ops.validation import inclusion_for
from tests.conftest import make_cameras, make_scene
from tests.float_parity import forward_tolerance, gradient_tolerance, largest_alpha_difference
from tests.test_op_stability import CASES


def cuda_test(fn):
    """Marks a test that needs a CUDA device (skipped with the reason "no CUDA device" otherwise)."""
    fn = pytest.mark.cuda(fn)
    return pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")(fn)


CUDA = torch.device("cuda")
PARAMS = ("means", "normals", "scales", "opacities", "features")


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max|a - b| / max|b| (b the CPU value; 0 when both are exactly equal)."""
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    diff = float((a - b).abs().max()) if a.numel() else 0.0
    if diff == 0.0:
        return 0.0
    return diff / max(float(b.abs().max()), 1e-300)


def _proj_to(proj, device):
    return type(proj)(**{f.name: getattr(proj, f.name).to(device) for f in dataclasses.fields(proj)})


def _setup(N, seed, B=2, W=24, H=20, dtype=torch.float64, **kw):
    sc = make_scene(N, seed, dtype=dtype, **kw)
    V, K = make_cameras(B, W, H, dtype=dtype)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    return sc, V, K, proj


# --------------------------------------------------------------------------------------------------------
# Sampling


@cuda_test
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("N,m,scale,order", [(200, 16, (0.04, 0.15), 8), (2000, 8, (0.01, 0.04), 8),
                                             (2000, 8, (0.01, 0.04), 0), (150, 1, (0.04, 0.15), 8)])
def test_sample_law_matches_cpu(dtype, N, m, scale, order):
    """Same projected inputs and seed: the same SPS sample law as the CPU backend (assert_same_sample_law: the
    two searches differ, so do their work counts, and an eps-event may differ on a few pixels)."""
    _, _, K, proj = _setup(N, seed=N + m, dtype=dtype, scale=scale, W=40, H=32)
    for seed in (0, 3):
        cpu = sample(proj, K, 40, 32, samples=m, eps=0.01, seed=seed, hermite_order=order)
        gpu = sample(_proj_to(proj, CUDA), K.to(CUDA), 40, 32, samples=m, eps=0.01, seed=seed, hermite_order=order)
        assert gpu[0].device.type == CUDA.type
        assert_same_sample_law([t.cpu() for t in gpu], cpu, 0.01, proj, seed)
    if N == 2000:
        assert int(cpu[3].max()) < N, "the case is meant to exercise pruning"


@cuda_test
def test_large_samples_law_matches_cpu():
    """samples = 300 (beyond any shared-memory heap) on 400 points: the CPU's sample law."""
    _, _, K, proj = _setup(400, seed=11, B=1, W=20, H=16, dtype=torch.float32)
    cpu = sample(proj, K, 20, 16, samples=300, seed=1)
    gpu = sample(_proj_to(proj, CUDA), K.to(CUDA), 20, 16, samples=300, seed=1)
    assert_same_sample_law([t.cpu() for t in gpu], cpu, 0.01, proj, 1)
    assert bool((cpu[0] >= 0).sum(-1).max() == 300), "some pixel should fill all 300 slots"


# --------------------------------------------------------------------------------------------------------
# Compositing and its backward on a fixed sample


def _composite_grads(proj, feat, bg, K, idx, probs, composite, estimator, weights):
    leaves = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, proj.amps, proj.normals_cam,
                                                             proj.plane_offsets, proj.depths, feat, bg)]
    p = type(proj)(*leaves[:6], proj.sigma2, proj.valid)
    img, alpha, depth = composite_sample(p, leaves[6], K, idx, probs, background=leaves[7], composite=composite,
                                         estimator=estimator)
    wi, wa, wd = weights
    loss = (img * wi).sum() + (alpha * wa).sum() + (depth * wd).sum()
    return (img, alpha, depth), torch.autograd.grad(loss, leaves)


@cuda_test
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("composite", ["alpha", "additive"])
@pytest.mark.parametrize("estimator", ["ht", "paper", "sampled"])
@pytest.mark.parametrize("m,C", [(8, 3), (40, 11)])
def test_composite_forward_and_gradients_match_cpu(dtype, composite, estimator, m, C):
    """Forward and every gradient (projected parameters, features, background) within the float analysis's bounds
    (tests/float_parity.py) on this scene and sample."""
    sc, _, K, proj = _setup(300, seed=5, B=2, W=32, H=24, dtype=dtype)
    feat = torch.randn(300, C, generator=torch.Generator().manual_seed(2), dtype=dtype)  # signed features
    bg = torch.linspace(0.1, 0.9, C, dtype=dtype)
    idx, probs, _, _ = sample(proj, K, 32, 24, samples=m, seed=4)
    assert bool((probs[idx >= 0] < 1).any()), "the sample should be a proper subsample"
    g = torch.Generator().manual_seed(0)
    weights = [torch.randn(2, 24, 32, c, generator=g, dtype=dtype) for c in (C, 1, 1)]
    out_c, grads_c = _composite_grads(proj, feat, bg, K, idx, probs, composite, estimator, weights)
    out_g, grads_g = _composite_grads(_proj_to(proj, CUDA), feat.to(CUDA), bg.to(CUDA), K.to(CUDA), idx.to(CUDA),
                                      probs.to(CUDA), composite, estimator, [w.to(CUDA) for w in weights])
    for name, a, b in zip(("image", "alpha", "depth"), out_g, out_c):
        assert rel_err(a, b) <= forward_tolerance(proj, feat, bg, idx, probs, composite, b), (name, rel_err(a, b))
    grad_tol = gradient_tolerance(largest_alpha_difference(proj, dtype), idx, dtype)
    names = ("means2d", "conics", "amps", "normals_cam", "plane_offsets", "depths", "features", "background")
    for name, a, b in zip(names, grads_g, grads_c):
        assert rel_err(a, b) <= grad_tol, (name, rel_err(a, b))


@cuda_test
@pytest.mark.parametrize("composite", ["alpha", "additive"])
@pytest.mark.parametrize("estimator", ["ht", "paper", "sampled"])
def test_splat_end_to_end_matches_cpu(composite, estimator):
    """``splat``'s stages on each device (projection included), float64: the CPU's sample law; and the CPU's
    sample composited on the GPU: forward and the gradients of every input within the float analysis's bounds
    (tests/float_parity.py; the two projections agree to float64 rounding, far below them)."""
    W, H = 28, 22
    sc = make_scene(250, 9, C=4, dtype=torch.float64)
    V, K = make_cameras(3, W, H, dtype=torch.float64)
    bg = torch.tensor([0.1, 0.5, 0.9, 0.3], dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    wi, wa, wd = (torch.randn(3, H, W, c, generator=g, dtype=torch.float64) for c in (4, 1, 1))
    kw = dict(samples=12, eps=0.01, seed=7, inclusion=inclusion_for(estimator))
    proj_c = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    cpu_sample = sample(proj_c, K, W, H, **kw)
    gpu_sample = sample(_proj_to(proj_c, CUDA), K.to(CUDA), W, H, **kw)
    assert_same_sample_law([t.cpu() for t in gpu_sample], cpu_sample, 0.01, proj_c, 7, inclusion=kw["inclusion"])

    def run(device):
        ps = [t.to(device).requires_grad_() for t in (*(sc[n] for n in PARAMS), V, bg)]
        proj = project(*ps[:4], ps[5], K.to(device), near=0.01, far=1e10, lowpass=1.0)
        img, alpha, depth = composite_sample(proj, ps[4], K.to(device), cpu_sample[0].to(device),
                                             cpu_sample[1].to(device), background=ps[6], composite=composite,
                                             estimator=estimator)
        loss = (img * wi.to(device)).sum() + (alpha * wa.to(device)).sum() + (depth * wd.to(device)).sum()
        return (img, alpha, depth), torch.autograd.grad(loss, ps)

    out_c, grads_c = run(torch.device("cpu"))
    out_g, grads_g = run(CUDA)
    idx, probs = cpu_sample[0], cpu_sample[1]
    for name, a, b in zip(("image", "alpha", "depth"), out_g, out_c):
        assert rel_err(a, b) <= forward_tolerance(proj_c, sc["features"], bg, idx, probs, composite, b), name
    grad_tol = gradient_tolerance(largest_alpha_difference(proj_c, torch.float64), idx, torch.float64)
    for name, a, b in zip((*PARAMS, "viewmats", "background"), grads_g, grads_c):
        assert rel_err(a, b) <= grad_tol, (name, rel_err(a, b))


@cuda_test
def test_cuda_is_deterministic():
    """Two CUDA runs give bitwise identical outputs and gradients (no atomics in the accumulations)."""
    sc = make_scene(500, 4, dtype=torch.float32)
    V, K = make_cameras(2, 40, 30, dtype=torch.float32)

    def run():
        ps = [sc[n].to(CUDA).requires_grad_() for n in PARAMS]
        out = splat(*ps, V.to(CUDA), K.to(CUDA), 40, 30, samples=16, seed=2)
        return [out.image, out.indices, *torch.autograd.grad(out.image.square().sum(), ps)]

    for a, b in zip(run(), run()):
        assert torch.equal(a, b)


# --------------------------------------------------------------------------------------------------------
# Dense reference on CUDA


@cuda_test
@pytest.mark.parametrize("composite", ["alpha", "additive"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dense_reference_runs_on_cuda_and_matches_full_sample(composite, dtype):
    """The oracle runs on CUDA, equals itself on the CPU, and equals the CUDA op with samples >= N."""
    W, H = 20, 16
    sc = {k: v.to(CUDA) for k, v in make_scene(40, 1, C=5, dtype=dtype).items()}
    V, K = (t.to(CUDA) for t in make_cameras(3, W, H, dtype=dtype))
    bg = torch.linspace(0.1, 0.9, 5, dtype=dtype, device=CUDA)
    args = (*(sc[n] for n in PARAMS), V, K, W, H)
    ref = splat_dense(*args, composite=composite, background=bg)
    ref_cpu = splat_dense(*(a.cpu() if torch.is_tensor(a) else a for a in args), composite=composite,
                          background=bg.cpu())
    out = splat(*args, samples=40, composite=composite, background=bg)
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    for name in ("image", "alpha", "depth", "total"):
        a, b = getattr(out, name), getattr(ref, name)
        assert a.device.type == b.device.type == CUDA.type
        assert rel_err(b, getattr(ref_cpu, name)) <= tol, name
        scale = max(1.0, float(b.abs().max()))
        assert torch.allclose(a, b, atol=1e-5 * scale, rtol=0), (name, float((a - b).abs().max()))
    assert bool((out.probs[out.indices >= 0] == 1).all())


# --------------------------------------------------------------------------------------------------------
# Stability cases of tests/test_op_stability.py on CUDA


def _run_cuda(sc, V, K, W, H, **kw):
    ps = [t.to(CUDA).requires_grad_() for t in (*(sc[n] for n in PARAMS), V)]
    bg = torch.full((sc["features"].shape[1],), 0.5, dtype=V.dtype, device=CUDA, requires_grad=True)
    out = splat(*ps, K.to(CUDA), W, H, background=bg, **kw)
    for name in ("image", "alpha", "depth", "total", "probs"):
        assert bool(torch.isfinite(getattr(out, name)).all()), f"{name} has NaN/Inf"
    assert bool(((out.alpha >= 0) & (out.alpha <= 1)).all()) or kw.get("composite") == "additive"
    loss = out.image.square().sum() + out.alpha.sum() + out.depth.sum()
    for g in torch.autograd.grad(loss, ps + [bg], allow_unused=True):
        assert g is None or bool(torch.isfinite(g).all()), "gradient has NaN/Inf"
    return out


@cuda_test
@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("composite,estimator", [("alpha", "ht"), ("additive", "paper"), ("alpha", "sampled")])
def test_stability_cases_on_cuda(case, composite, estimator):
    sc = make_scene(20, 0, dtype=torch.float32)
    CASES[case](sc)
    V, K = make_cameras(2, 16, 12, dtype=torch.float32)
    _run_cuda(sc, V, K, 16, 12, samples=8, composite=composite, estimator=estimator)


@cuda_test
@pytest.mark.parametrize("N", [0, 1, 3])
def test_few_points_and_fewer_than_samples_on_cuda(N):
    sc = make_scene(N, 0, dtype=torch.float32)
    V, K = make_cameras(2, 9, 7, dtype=torch.float32)
    out = _run_cuda(sc, V, K, 9, 7, samples=5)
    assert out.indices.shape == (2, 7, 9, 5)
    assert bool((out.indices[..., N:] == -1).all())


@cuda_test
@pytest.mark.parametrize("W,H", [(1, 1), (1, 17), (23, 2), (40, 9)])
def test_odd_image_sizes_on_cuda(W, H):
    sc = make_scene(30, 0, dtype=torch.float32)
    V, K = make_cameras(1, W, H, dtype=torch.float32, focal=20.0)
    assert _run_cuda(sc, V, K, W, H, samples=4).image.shape == (1, H, W, 3)


@cuda_test
def test_many_samples_and_channels_on_cuda():
    """samples=200 and 33 channels (the per-point pass accumulates features in chunks): matches the CPU."""
    sc = make_scene(50, 0, C=33, dtype=torch.float64)
    V, K = make_cameras(3, 8, 8, dtype=torch.float64)
    _run_cuda(sc, V, K, 8, 8, samples=200)
    feats = sc["features"].clone().requires_grad_()
    ref = splat(sc["means"], sc["normals"], sc["scales"], sc["opacities"], feats, V, K, 8, 8, samples=200,
                background=torch.full((33,), 0.5, dtype=torch.float64))
    g_ref = torch.autograd.grad(ref.image.square().sum(), feats)[0]
    feats_g = sc["features"].to(CUDA).requires_grad_()
    out = splat(*(sc[n].to(CUDA) for n in PARAMS[:4]), feats_g, V.to(CUDA), K.to(CUDA), 8, 8, samples=200,
                background=torch.full((33,), 0.5, dtype=torch.float64, device=CUDA))
    g = torch.autograd.grad(out.image.square().sum(), feats_g)[0]
    assert out.image.shape == (3, 8, 8, 33)
    proj = project(*(sc[n] for n in PARAMS[:4]), V, K, near=0.01, far=1e10, lowpass=1.0)
    bg = torch.full((33,), 0.5, dtype=torch.float64)
    assert rel_err(out.image, ref.image) <= forward_tolerance(proj, feats, bg, ref.indices, ref.probs, "alpha",
                                                              ref.image)
    assert rel_err(g, g_ref) <= gradient_tolerance(largest_alpha_difference(proj, torch.float64), ref.indices,
                                                   torch.float64)


# --------------------------------------------------------------------------------------------------------
# 64-bit slot arithmetic


def _check_large_m(device, W, H, m_big, with_backward):
    """A 6-point scene covering the whole image rendered with m = 8 and with m = m_big: the sample, forward and
    (optionally) backward must be equal, and slots 8.. of the large run empty."""
    xs = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float32)
    means = torch.stack([torch.stack([x, torch.tensor(y), torch.tensor(0.0)]) for x in xs for y in (-1.0, 1.0)])
    normals = torch.tensor([[0.0, 0.0, -1.0]]).repeat(6, 1)
    scales = torch.full((6, 2), 0.3)
    opac = torch.linspace(0.4, 0.9, 6)
    feats = torch.rand(6, 3, generator=torch.Generator().manual_seed(0))
    V, K = make_cameras(1, W, H, dtype=torch.float32, focal=1.25 * W)  # the points reach the image corners

    def run(m):
        ps = [t.to(device).requires_grad_(with_backward) for t in (means, normals, scales, opac, feats)]
        out = splat(*ps, V.to(device), K.to(device), W, H, samples=m, seed=3)
        grads = torch.autograd.grad(out.image.sum() + out.depth.sum(), ps) if with_backward else []
        return out, grads

    small, g_small = run(8)
    assert bool((small.indices[0, -1, -1] >= 0).any()) and bool((small.indices[0, 0, 0] >= 0).any())
    big, g_big = run(m_big)
    assert big.indices.shape == (1, H, W, m_big)
    assert torch.equal(big.indices[..., :8], small.indices)
    assert bool((big.indices[..., 8:] == -1).all())
    assert torch.equal(big.probs[..., :8], small.probs)
    assert torch.equal(big.image, small.image) and torch.equal(big.depth, small.depth)
    assert len(g_big) == len(g_small)
    for a, b in zip(g_big, g_small):
        assert torch.equal(a, b)


def large_m_bytes(W: int, H: int, m: int, backward: bool) -> int:
    """GPU memory the large-m run allocates at its peak (the m = 8 run is negligible beside it), with a 10 % margin for
    the allocator's rounding: per slot the sample (int32 index, float32 pi: 8 bytes) and the sampler's heap scratch
    (float64 key, int32 id: 12 bytes) during sampling; with the backward, the sample, its two float32 per-slot
    derivatives (8), the entry sort's int32 keys, sorted keys and int64 order and entries (24): 40 bytes."""
    per_slot = 40 if backward else 8 + 12
    return int(1.1 * W * H * m * per_slot)


@cuda_test
def test_slot_offsets_beyond_2_31():
    """B·H·W·m > 2^31: the sample, the forward and the backward of a 2048² image with m = 513 equal those of
    m = 8 on the same scene (6 points, so both samples hold every point; slots 8.. must be empty).

    Skips unless the GPU has the memory the run allocates (large_m_bytes: about 47 GB for the forward, 95 GB with the
    backward); the backward part is skipped when only the forward fits."""
    W = H = 2048
    m_big = 513
    assert W * H * m_big > 2**31
    free, _ = torch.cuda.mem_get_info()
    need = large_m_bytes(W, H, m_big, backward=False)
    if free < need:
        pytest.skip(f"needs {need / 1e9:.0f} GB of free GPU memory, {free / 1e9:.0f} GB free")
    need_backward = large_m_bytes(W, H, m_big, backward=True)
    with_backward = free >= need_backward
    _check_large_m(CUDA, W, H, m_big, with_backward)
    if not with_backward:
        pytest.skip(f"forward checked; the backward needs {need_backward / 1e9:.0f} GB of free GPU memory, "
                    f"{free / 1e9:.0f} GB free")


@cuda_test
def test_cuda_step_reads_back_three_times_whatever_the_views():
    """A step (splat forward of B views in one call, L1, backward) reads back to the host three times, for 1 and
    for 6 views (torch.cuda.set_sync_debug_mode counts every read): the input value checks together, the
    projection's float-hazard checks together (ops/value_checks.py), and the sampler's one size read (the tile
    item offsets and the coefficient total; the trees' valid counts stay on the device). Nothing else
    synchronises."""
    sc = make_scene(3000, 8, dtype=torch.float32, scale=(0.01, 0.05))
    ps = [sc[n].to(CUDA).requires_grad_() for n in PARAMS]

    def syncs(B: int) -> list[str]:
        V, K = (t.to(CUDA) for t in make_cameras(B, 48, 40, dtype=torch.float32))
        target = torch.rand(B, 40, 48, 3, device=CUDA)
        seed = torch.arange(B) + 7  # per-camera seeds on the host, as the fitter passes them
        torch.cuda.synchronize()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                out = splat(*ps, V, K, 48, 40, samples=16, seed=seed)
                (out.image - target).abs().mean().backward()
            finally:
                torch.cuda.set_sync_debug_mode("default")
        return [f"{w.filename}:{w.lineno}: {w.message}" for w in caught if "synchroniz" in str(w.message)]

    for B in (1, 6):
        found = syncs(B)
        assert len(found) == 3, "\n".join(found)


# --------------------------------------------------------------------------------------------------------
# Host emulation of the CUDA launch code (runs without a GPU)


@pytest.fixture(scope="module")
def emulated():
    """splat_cuda.cu built by the host compiler in its emulation mode, cached like the real backends (the
    source-hash define makes it rebuild when any native source or core header changes). Its sampling launches
    hold at most 4 KiB of per-pixel bins (256 tile items) instead of 256 MB, so every scene below is sampled
    in several launches, some of them one tile with more items than that; and its tree builds sort the keys of at
    most 4 cameras at once, so that calls over more cameras take several sorts."""
    from torch.utils.cpp_extension import load

    sources = [str(CSRC / "cuda" / "bindings.cpp"), str(CSRC / "cuda" / "emulate.cpp")]
    flags = ["-O3", f"-std={cxx_standard()}", "-DNSPLAT_CUDA_EMULATE", f"-DNSPLAT_SOURCE_HASH={source_hash()}",
             "-DNSPLAT_BIN_SCRATCH_BYTES=4096", "-DNSPLAT_SORT_CAMERAS=4"]
    return load(name="nsplat_cuda_emu", sources=sources, extra_cflags=flags, extra_include_paths=[str(CSRC)],
                build_directory=str(build_dir("cuda_emu")), verbose=False)


def _emulate(monkeypatch, emulated):
    """Route the custom ops' CPU kernels through the emulated CUDA module, as the CUDA kernels call the CUDA one
    (device sort of the backward's slots, no atomic-scatter backward)."""
    monkeypatch.setattr(library, "native", lambda kind: library.Native(emulated, counting_sort=False,
                                                                        scatter_backward=False))


def _sorted_keys(lam, m, seed, camera, width, stratified):
    """Each pixel's sorted log keys ``[P, m + 1]`` (``sps_bruteforce``'s; stratified draws: ops/rng.py)."""
    if not stratified:
        return sps_bruteforce(lam, m, seed, camera)[1]
    P, N = lam.shape
    u = stratified_uniforms(seed, camera, np.arange(P), np.arange(N), width)
    with np.errstate(divide="ignore"):
        keys = np.where(lam.numpy() > 0, np.log(u) - np.log(lam.numpy()), np.inf)
    keys = np.sort(keys, axis=1)[:, : m + 1]
    return np.pad(keys, ((0, 0), (0, m + 1 - keys.shape[1])), constant_values=np.inf)


def assert_same_sample_law(got, ref, eps, proj, seed, inclusion="threshold", stratified=False):
    """Two backends' samples of the same projected scene ``proj`` and seed (``sample``'s outputs). Each is the exact
    SPS sample, with the exact threshold xi_(m+1), except on a fraction <= eps of the pixels, so they differ on at
    most ~2 eps of them (binomial bound at 4 sigma, + 1): a pixel differs when its index sets differ or, with
    threshold inclusion, when a point's pi = min(1, lambda xi_(m+1)) does (beyond 1e-6). (The "pips" pi are a
    function of each backend's own Lambda_hat, which is checked instead; tests/test_op_sampler.py checks their
    formula.) Each backend's Lambda_hat is within its documented bound of the dense total
    (|Lambda_hat - Lambda| <= eps / xi_(m) wherever the sample is full, + 1e-6 relative; a pixel reported empty,
    Lambda_hat = 0, is one whose total is below the floor MIN_TOTAL)."""
    (gi, gp, gt, _), (ri, rp, rt, _) = got, ref
    B, H, W, m = gi.shape
    differ = 0
    for b in range(B):
        lam = size_measures(proj, b, W, H)
        # a [B] seed: camera b draws as camera 0 of a call with seed[b] (tests/test_op_camera_seeds.py)
        keys = _sorted_keys(lam, m, *((int(seed), b) if torch.as_tensor(seed).dim() == 0 else (int(seed[b]), 0)), W,
                            stratified)
        dense = lam.sum(1).numpy()
        for idx, tot in ((gi[b], gt[b]), (ri[b], rt[b])):
            full = (idx.reshape(-1, m) >= 0).all(1).numpy()
            est = tot.reshape(-1).double().numpy()
            bound = np.where(full, eps * np.exp(-keys[:, m - 1]), 0.0) + 1e-6 * dense + np.where(est == 0, MIN_TOTAL, 0)
            assert np.all(np.abs(est - dense) <= bound), float(np.max(np.abs(est - dense) - bound))
        a_idx, a_p, b_idx, b_p = (t[b].reshape(-1, m) for t in (gi, gp, ri, rp))
        for p in range(a_idx.shape[0]):
            a, c = a_idx[p][a_idx[p] >= 0].tolist(), b_idx[p][b_idx[p] >= 0].tolist()
            if set(a) != set(c):
                differ += 1
                continue
            if inclusion == "threshold":
                pa = dict(zip(a, a_p[p][: len(a)].double().tolist()))
                pc = dict(zip(c, b_p[p][: len(c)].double().tolist()))
                differ += not all(abs(pa[k] - pc[k]) <= 1e-6 * pc[k] + 1e-12 for k in a)
    n = gi.numel() // m
    allowed = 2 * eps * n + 4 * (2 * eps * n) ** 0.5 + 1
    assert differ <= allowed, f"{differ} of {n} pixels differ (allowed {allowed:.1f})"


def _both(emulated, monkeypatch, sc, V, K, W, H, *, samples, eps=0.01, seed=0, composite="alpha", estimator="ht",
          stratified=False):
    """The sample of each backend (CPU, emulated CUDA) for ``splat``'s projection of ``sc``, and compositing +
    backward of the CPU's sample through each backend (the same core code: bitwise equal)."""
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    kw = dict(samples=samples, eps=eps, seed=seed, inclusion=inclusion_for(estimator), stratified=stratified)
    ref_sample = sample(proj, K, W, H, **kw)
    C = sc["features"].shape[-1]
    g = torch.Generator().manual_seed(1)
    wi, wa, wd = (torch.randn(V.shape[0], H, W, c, generator=g, dtype=V.dtype) for c in (C, 1, 1))
    idx, probs = ref_sample[0], ref_sample[1]

    def composite_run():
        leaves = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, proj.amps, proj.normals_cam,
                                                                 proj.plane_offsets, proj.depths, sc["features"])]
        bg = torch.linspace(0.2, 0.7, C, dtype=V.dtype).requires_grad_()
        p = type(proj)(*leaves[:6], proj.sigma2, proj.valid)
        img, alpha, depth = composite_sample(p, leaves[6], K, idx, probs, background=bg, composite=composite,
                                             estimator=estimator)
        loss = (img * wi).sum() + (alpha * wa).sum() + (depth * wd).sum()
        return (img, alpha, depth), torch.autograd.grad(loss, leaves + [bg])

    ref = composite_run()
    _emulate(monkeypatch, emulated)
    got_sample = sample(proj, K, W, H, **kw)
    got = composite_run()
    monkeypatch.undo()
    return (got_sample, ref_sample, proj), (got, ref)


def _assert_identical(got, ref):
    (outs, grads), (outs_ref, grads_ref) = got, ref
    for name, a, b in zip(("image", "alpha", "depth"), outs, outs_ref):
        assert torch.equal(a, b), name
    for name, a, b in zip(("mu", "con", "amp", "nrm", "off", "zc", "features", "background"), grads, grads_ref):
        assert torch.equal(a, b), name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("composite,estimator", [("alpha", "ht"), ("alpha", "paper"), ("alpha", "sampled"),
                                                 ("additive", "ht"), ("additive", "paper")])
def test_emulated_cuda_launch_code_equals_cpu(emulated, monkeypatch, dtype, composite, estimator):
    """Tree build and sampling of splat_cuda.cu, run on the host, draw the same SPS law as the CPU backend
    (assert_same_sample_law), pruning and Hermite expansions included; its compositing and both backward passes
    give the same bits as the CPU backend on the same sample (same compiler and core code)."""
    sc = make_scene(1500, 3, C=3, dtype=dtype, scale=(0.01, 0.05))
    V, K = make_cameras(2, 36, 28, dtype=dtype)
    (got, ref, proj), composited = _both(emulated, monkeypatch, sc, V, K, 36, 28, samples=8, eps=0.01,
                                         composite=composite, estimator=estimator, seed=5)
    assert_same_sample_law(got, ref, 0.01, proj, 5, inclusion=inclusion_for(estimator))
    _assert_identical(*composited)
    assert int(ref[3].max()) < 1500, "the scene is meant to exercise pruning"


def test_emulated_cuda_per_camera_seeds_sample_as_one_call_per_view(emulated, monkeypatch):
    """With one seed per camera the CUDA launch code samples each camera of a call as that camera alone with its
    seed (bitwise), and draws the CPU backend's SPS law."""
    sc = make_scene(600, 3, C=3, scale=(0.01, 0.05))
    V, K = make_cameras(3, 24, 20)
    seeds = torch.tensor([3, 2**62 + 1, 9])
    (got, ref, proj), _ = _both(emulated, monkeypatch, sc, V, K, 24, 20, samples=6, seed=seeds)
    assert_same_sample_law(got, ref, 0.01, proj, seeds)
    _emulate(monkeypatch, emulated)
    for b in range(3):
        one = type(proj)(**{f.name: getattr(proj, f.name)[b:b + 1] for f in dataclasses.fields(proj)})
        alone = sample(one, K[b:b + 1], 24, 20, samples=6, eps=0.01, seed=int(seeds[b]))
        for a, c in zip(alone, got):
            assert torch.equal(a, c[b:b + 1])
    monkeypatch.undo()


@pytest.mark.parametrize("lanes", [1, 3])
def test_emulated_cuda_camera_groups_sample_as_one_call_per_view(emulated, monkeypatch, lanes):
    """A call over more cameras than one launch takes (kCameraGroup = 16 in splat_cuda.cu: the tile and pixel
    passes run per group of cameras) samples each camera as that camera alone (bitwise). Every call, over 18 cameras
    or one, with trees of 0, 1, 2 or all points, reads sizes back to the host once (the valid counts stay on the
    device)."""
    sc = make_scene(300, 5, C=3, scale=(0.01, 0.05))
    B, W, H = 18, 9, 6
    V, K = make_cameras(B, W, H)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    # cameras whose trees have no point, one point (no internal node) and two points beside full ones
    for b, keep in ((3, 0), (6, 1), (13, 2)):
        proj.amps[b, keep:] = 0
    seeds = torch.arange(B) * 7 + 1
    _emulate(monkeypatch, emulated)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", str(lanes))
    reads = emulated.host_reads()
    got = sample(proj, K, W, H, samples=4, eps=0.01, seed=seeds)
    assert emulated.host_reads() - reads == 1
    assert int((got[0] >= 0).sum()) > 0
    for b in range(B):
        one = type(proj)(**{f.name: getattr(proj, f.name)[b:b + 1] for f in dataclasses.fields(proj)})
        reads = emulated.host_reads()
        alone = sample(one, K[b:b + 1], W, H, samples=4, eps=0.01, seed=int(seeds[b]))
        assert emulated.host_reads() - reads == 1, b
        for a, c in zip(alone, got):
            assert torch.equal(a, c[b:b + 1])
    monkeypatch.undo()


def test_emulated_cuda_tree_builds_take_one_launch_per_step_for_all_cameras(emulated, monkeypatch):
    """The sampler builds the trees of all cameras of a call together: a call over 4 cameras takes as many launches
    as one over a single camera (the tree steps, tile passes and, the scene being small, one sampling launch), and 8
    cameras take three more, those of a second key sort (the emulation sorts at most 4 cameras' keys at once)."""
    sc = make_scene(12, 11, C=3, scale=(0.01, 0.05))
    V, K = make_cameras(8, 8, 8)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    _emulate(monkeypatch, emulated)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", "1")

    def launches(B: int) -> int:
        one = type(proj)(**{f.name: getattr(proj, f.name)[:B] for f in dataclasses.fields(proj)})
        before = emulated.launches()
        out = sample(one, K[:B], 8, 8, samples=4, eps=0.01, seed=3)
        assert int((out[0] >= 0).sum()) > 0
        return emulated.launches() - before

    assert launches(4) == launches(1)
    assert launches(8) == launches(1) + 3
    monkeypatch.undo()


@pytest.mark.parametrize("lanes", [1, 2, 3, 8, 16])
@pytest.mark.parametrize("stratified,inclusion", [(False, "threshold"), (True, "threshold"), (False, "pips")])
def test_emulated_cuda_pixel_lanes_draw_the_cpu_law(emulated, monkeypatch, lanes, stratified, inclusion):
    """Several threads per pixel (tile.h, "Lanes": lane j searches the items j mod L with the budget eps / L and
    the floor kMinTotal / L; a lane stopped by its floor searches again unless the pixel is certified below the
    floor; the heaps merge into the m smallest keys): the CPU backend's SPS law and Lambda_hat bounds whatever
    the lane count, on a scene with pruning and with pixels in the floor's band; bitwise the same run to run."""
    sc = make_scene(2000, 4, C=3, scale=(0.01, 0.05))
    V, K = make_cameras(2, 40, 32)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    kw = dict(samples=10, eps=0.01, seed=11, stratified=stratified, inclusion=inclusion)
    ref = sample(proj, K, 40, 32, **kw)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", str(lanes))
    _emulate(monkeypatch, emulated)
    got = sample(proj, K, 40, 32, **kw)
    again = sample(proj, K, 40, 32, **kw)
    monkeypatch.undo()
    assert all(torch.equal(a, b) for a, b in zip(got, again))
    assert_same_sample_law(got, ref, 0.01, proj, 11, inclusion=inclusion, stratified=stratified)
    total, work = got[2], got[3]
    assert int(work.max()) < 2000, "the scene is meant to exercise pruning"
    lam = torch.stack([size_measures(proj, b, 40, 32).sum(1) for b in range(2)]).reshape(total.shape)
    band = (lam > MIN_TOTAL / 4) & (lam < 4 * MIN_TOTAL)
    assert int(band.sum()) >= 20, "the scene is meant to have pixels near the floor"
    assert bool((total[lam < MIN_TOTAL / 2] == 0).all()) and bool((total[lam > 2 * MIN_TOTAL] > 0).all())


@pytest.mark.parametrize("lanes,m", [(2, 1), (2, 2), (4, 2), (3, 5)])
def test_emulated_cuda_pixel_lanes_small_samples(emulated, monkeypatch, lanes, m):
    """Small m against the lanes' heaps: the pixel's xi_(m+1) is often the key right after one lane's full heap
    (that lane's own threshold), which the inclusion probabilities min(1, lambda xi_(m+1)) must use."""
    sc = make_scene(1200, 7, C=3, scale=(0.01, 0.05))
    V, K = make_cameras(2, 32, 24)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    ref = sample(proj, K, 32, 24, samples=m, eps=0.01, seed=3)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", str(lanes))
    _emulate(monkeypatch, emulated)
    got = sample(proj, K, 32, 24, samples=m, eps=0.01, seed=3)
    monkeypatch.undo()
    assert_same_sample_law(got, ref, 0.01, proj, 3)


def _kway_merge(keys, ids, counts, m):
    """The lanes' sorted heaps of one pixel merged one entry at a time, the smallest (key, id) head first: the m
    smallest entries and the (m+1)-th smallest key (None when there are at most m entries)."""
    at, out = [0] * len(keys), []
    while True:
        heads = [((keys[j][at[j]], ids[j][at[j]]), j) for j in range(len(keys)) if at[j] < counts[j]]
        if not heads:
            return out, None
        entry, j = min(heads)
        if len(out) == m:
            return out, entry[0]
        out.append(entry)
        at[j] += 1


@pytest.mark.parametrize("lanes,m", [(2, 1), (2, 6), (3, 4), (5, 9), (16, 3)])
def test_emulated_cuda_lane_merge_is_the_sequential_merge(emulated, lanes, m):
    """The sampler's merge of the lanes' sorted heaps (each entry placed at its rank, found by binary searches in the
    other lanes' heaps) gives exactly the sequential k-way merge's m smallest entries and (m+1)-th key, on heaps of
    every size from empty to full, with tied keys (ordered by id) and infinite keys."""
    rng = np.random.default_rng(lanes * 100 + m)
    P = 60
    values = np.array([-3.0, -1.5, -1.5, -1.5, 0.25, 2.0, np.inf])
    keys = np.sort(rng.choice(values, (P, lanes, m)), axis=2)
    ids = np.stack([rng.permutation(10 * lanes * m)[: lanes * m].reshape(lanes, m) for _ in range(P)])
    counts = rng.integers(0, m + 1, (P, lanes))
    for p, j in np.ndindex(P, lanes):
        order = sorted(range(m), key=lambda i: (keys[p, j, i], ids[p, j, i]))
        keys[p, j], ids[p, j] = keys[p, j, order], ids[p, j, order]
    got_key, got_idx, got_rest = emulated.merge_lanes(torch.from_numpy(keys), torch.from_numpy(ids).int(),
                                                      torch.from_numpy(counts).int(), m)
    for p in range(P):
        want, rest = _kway_merge(keys[p], ids[p], counts[p], m)
        n = len(want)
        assert got_key[p, :n].tolist() == [k for k, _ in want] and got_idx[p, :n].tolist() == [i for _, i in want]
        assert bool(got_idx[p, n:].eq(-1).all())
        assert (rest is None and bool(got_rest[p].isnan())) or float(got_rest[p]) == rest


def test_emulated_cuda_pixel_lanes_setting_is_checked(emulated, monkeypatch):
    sc = make_scene(50, 1, C=3)
    V, K = make_cameras(1, 8, 8)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", "0")
    _emulate(monkeypatch, emulated)
    with pytest.raises(RuntimeError, match=r"NSPLAT_CUDA_PIXEL_LANES must be an integer in \[1, 16\], got '0'"):
        sample(proj, K, 8, 8, samples=4)


@pytest.mark.parametrize("N,m,C,W,H", [(0, 5, 3, 9, 7), (1, 5, 3, 9, 7), (3, 5, 3, 9, 7), (60, 300, 3, 10, 8),
                                       (50, 40, 33, 8, 8), (40, 4, 2, 1, 17), (40, 4, 2, 23, 2)])
def test_emulated_cuda_edge_sizes_equal_cpu(emulated, monkeypatch, N, m, C, W, H):
    """Empty and tiny scenes, samples > N and large m, many channels (pass 2's chunks), odd image sizes."""
    sc = make_scene(N, 2, C=C, dtype=torch.float64)
    V, K = make_cameras(3, W, H, dtype=torch.float64)
    (got, ref, proj), composited = _both(emulated, monkeypatch, sc, V, K, W, H, samples=m, seed=1)
    assert_same_sample_law(got, ref, 0.01, proj, 1)
    _assert_identical(*composited)


@pytest.mark.parametrize("estimator", ["ht", "paper"])
@pytest.mark.parametrize("C", [3, 11])
def test_emulated_cuda_per_camera_features_equal_cpu(emulated, monkeypatch, estimator, C):
    """Features ``[B,N,C]`` (camera b sees its own row): compositing and both backward passes of the CUDA launch
    code give the CPU backend's bits, the feature gradient per camera (11 channels: pass 2's chunks)."""
    sc = make_scene(400, 5, C=C, scale=(0.02, 0.08))
    sc["features"] = torch.rand(3, 400, C, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    V, K = make_cameras(3, 20, 16)
    (got, ref, proj), composited = _both(emulated, monkeypatch, sc, V, K, 20, 16, samples=6, estimator=estimator,
                                         seed=2)
    assert_same_sample_law(got, ref, 0.01, proj, 2, inclusion=inclusion_for(estimator))
    _assert_identical(*composited)
    assert composited[1][1][6].shape == (3, 400, C)


@pytest.mark.parametrize("case", sorted(CASES))
def test_emulated_cuda_stability_cases_equal_cpu(emulated, monkeypatch, case):
    sc = make_scene(20, 0, dtype=torch.float32)
    CASES[case](sc)
    V, K = make_cameras(2, 16, 12, dtype=torch.float32)
    (got, ref, proj), composited = _both(emulated, monkeypatch, sc, V, K, 16, 12, samples=8, estimator="paper")
    assert_same_sample_law(got, ref, 0.01, proj, 0, inclusion="pips")
    _assert_identical(*composited)


# --------------------------------------------------------------------------------------------------------
# The projection and view colour kernels (projection_cuda.cu): emulated on the host, and on a GPU

PROJ_FIELDS = ("means2d", "conics", "amps", "normals_cam", "plane_offsets", "depths", "sigma2")


def _projection_inputs(dtype: torch.dtype, N: int = 1100, B: int = 3) -> list[torch.Tensor]:
    """Surfels ``[N]`` (more than two blocks of the camera-gradient sums) and ``B`` cameras; some points behind
    the near plane or beyond far, some facing away (back-face culling)."""
    sc = make_scene(N, 4, dtype=dtype)
    V, K = make_cameras(B, 64, 48, dtype=dtype)
    sc["means"][:10, 2] = -3.0
    sc["means"][10:20, 2] = 40.0
    sc["normals"][20:60, 2] *= -1.0
    return [sc["means"], sc["normals"], sc["scales"] * torch.tensor([1.0, 1.6], dtype=dtype), sc["opacities"], V, K]


def _projection_run(x: list[torch.Tensor], cull: bool) -> tuple[list[torch.Tensor], tuple[torch.Tensor, ...]]:
    """``project``'s outputs and the inputs' gradients for a fixed random linear function of every output."""
    leaves = [t.detach().clone().requires_grad_() for t in x]
    out = project(*leaves, near=0.5, far=30.0, lowpass=0.3, backface_cull=cull)
    g = torch.Generator().manual_seed(7)
    loss = sum((getattr(out, f) * torch.randn(getattr(out, f).shape, generator=g, dtype=x[0].dtype)
                .to(x[0].device)).sum() for f in PROJ_FIELDS)
    return [getattr(out, f) for f in (*PROJ_FIELDS, "valid")], torch.autograd.grad(loss, leaves)


def _view_colour_inputs(degree: int, dtype: torch.dtype, N: int = 1100) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(degree)
    features = torch.randn(N, 3 * (degree + 1) ** 2, generator=g, dtype=dtype) * 0.4
    features[:, :3] += 0.3  # some colours clamp at 0, most do not
    V, _ = make_cameras(2, 32, 32, dtype=dtype)
    return [features, torch.rand(N, 3, generator=g, dtype=dtype) - 0.5, V[1]]


def _view_colour_run(x: list[torch.Tensor]) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    from nsplat.render.sh import view_colour

    leaves = [t.detach().clone().requires_grad_() for t in x]
    out = view_colour(*leaves)
    w = torch.randn(out.shape, generator=torch.Generator().manual_seed(3), dtype=out.dtype).to(out.device)
    return out, torch.autograd.grad((out * w).sum(), leaves)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_emulated_cuda_projection_equals_cpu(emulated, monkeypatch, dtype, cull):
    """The projection's CUDA launch code (one thread per pair; per-point backward; camera gradients summed over
    fixed blocks in the CPU's order) gives the CPU backend's bits, outputs and every input's gradient."""
    x = _projection_inputs(dtype)
    ref = _projection_run(x, cull)
    _emulate(monkeypatch, emulated)
    got = _projection_run(x, cull)
    monkeypatch.undo()
    assert 0 < int(ref[0][-1].sum()) < ref[0][-1].numel()  # culled and visible pairs
    for name, a, b in zip((*PROJ_FIELDS, "valid", "means", "normals", "scales", "opacities", "viewmats", "Ks"),
                          [*got[0], *got[1]], [*ref[0], *ref[1]]):
        assert torch.equal(a, b), name


@pytest.mark.parametrize("cull", [False, True])
def test_emulated_cuda_projection_matches_reference_float64(emulated, monkeypatch, cull):
    """Its float64 outputs and gradients against autograd through ``project_torch``."""
    from nsplat.ops.projection import project_torch

    x = _projection_inputs(torch.float64, N=300)
    _emulate(monkeypatch, emulated)
    got = _projection_run(x, cull)
    monkeypatch.undo()
    monkeypatch.setattr("nsplat.ops.projection.project_checked", lambda *a, **k: project_torch(*a, **k))
    ref = _projection_run(x, cull)
    for name, a, b in zip((*PROJ_FIELDS, "valid", "means", "normals", "scales", "opacities", "viewmats", "Ks"),
                          [*got[0], *got[1]], [*ref[0], *ref[1]]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10, msg=name)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_emulated_cuda_view_colour_equals_cpu_and_reference(emulated, monkeypatch, dtype, degree):
    """The view colour's CUDA launch code gives the CPU backend's bits; in float64 it matches autograd through
    ``view_colour_torch``."""
    from nsplat.render.sh import view_colour_torch

    x = _view_colour_inputs(degree, dtype)
    ref = _view_colour_run(x)
    _emulate(monkeypatch, emulated)
    got = _view_colour_run(x)
    monkeypatch.undo()
    assert 0 < int((ref[0] == 0).sum()) < ref[0].numel()  # the clamp is exercised
    for name, a, b in zip(("rgb", "features", "means", "viewmat"), [got[0], *got[1]], [ref[0], *ref[1]]):
        assert torch.equal(a, b), name
    if dtype == torch.float64:
        monkeypatch.setattr("nsplat.render.sh.view_colour", view_colour_torch)
        torch_ref = _view_colour_run(x)
        for name, a, b in zip(("rgb", "features", "means", "viewmat"), [got[0], *got[1]],
                              [torch_ref[0], *torch_ref[1]]):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-11, msg=name)


@cuda_test
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_cuda_projection_kernel_equals_cpu(dtype, cull):
    """The native CUDA projection against the CPU kernel (same core code; FMA contraction and CUDA's sqrt
    differ in the last bits), outputs and gradients."""
    x = _projection_inputs(dtype, N=5000, B=4)
    ref = _projection_run(x, cull)
    got = _projection_run([t.to(CUDA) for t in x], cull)
    assert torch.equal(got[0][-1].cpu(), ref[0][-1])
    tol = 1e-10 if dtype == torch.float64 else 1e-5
    for name, a, b in zip((*PROJ_FIELDS, "means", "normals", "scales", "opacities", "viewmats", "Ks"),
                          [*got[0][:-1], *got[1]], [*ref[0][:-1], *ref[1]]):
        assert rel_err(a, b) <= tol, name


@cuda_test
@pytest.mark.parametrize("degree", [1, 3])
def test_cuda_view_colour_kernel_equals_cpu(degree):
    x = _view_colour_inputs(degree, torch.float32, N=5000)
    ref = _view_colour_run(x)
    got = _view_colour_run([t.to(CUDA) for t in x])
    for name, a, b in zip(("rgb", "features", "means", "viewmat"), [got[0], *got[1]], [ref[0], *ref[1]]):
        assert rel_err(a, b) <= 1e-5, name
