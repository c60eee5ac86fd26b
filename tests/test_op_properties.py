"""Property-based tests of the op over its documented input domain (docs/op.md "Valid input domain"),
and the deterministic / non-deterministic backward.

Scenes are drawn by :func:`draw_case` through a small ``Draw`` interface, so that the same generator
feeds hypothesis here (60 shrinkable examples) and the long soak run in
``tools/properties_soak.py`` (numpy RNG, >= 10k scenes). The generator covers the domain's
edges: splat screen sizes from far below a pixel to 1e9 px (float32; 1e-20..1e12 px in float64),
depths over nine decades, coordinates offset by up to 1e6, opacities 0 / 1e-30 / 1, exactly and
nearly edge-on normals, coincident points, points behind the camera or at the near plane, 1-pixel
images, sample sizes above N, and the low-pass edge 1e-12 px² in float32 (0 in float64).
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nsplat.ops import composite_sample, project, splat
from tests.conftest import make_cameras, make_scene

# ----------------------------------------------------------------------------------------------- domain
#: Documented domain limits (docs/op.md); the generator draws up to and including these edges.
SIGMA_PX_MAX = {torch.float32: 1e9, torch.float64: 1e12}     # splat screen std-dev (pixels)
SIGMA_PX_MIN = {torch.float32: 1e-8, torch.float64: 1e-20}
#: Culled points (centre depth outside [near, far]) have their discarded intermediates zeroed, so any
#: finite f·s·(1 + |q_x| + |q_y|) is allowed; the draws go up to this (docs/op.md).
CULLED_FS_MAX = {torch.float32: 1e30, torch.float64: 1e150}
FAR = 1e10
LOWPASS = {torch.float32: (1e-12, 0.3, 1.0, 4.0), torch.float64: (0.0, 1e-12, 1.0)}
OFFSETS = (0.0, 0.0, 1.0, 1e3, 1e6)                             # world offset of scene and cameras
ESTIMATORS = ("ht", "paper", "sampled")
COMPOSITES = ("alpha", "additive")


class Draw:
    """Source of random choices: hypothesis' ``data.draw`` or a numpy ``Generator``."""

    def __init__(self, data: Any = None, rng: np.random.Generator | None = None) -> None:
        self.data, self.rng = data, rng

    def integer(self, lo: int, hi: int) -> int:
        if self.data is not None:
            return self.data.draw(st.integers(lo, hi))
        return int(self.rng.integers(lo, hi + 1))

    def uniform(self, lo: float, hi: float) -> float:
        if self.data is not None:
            return self.data.draw(st.floats(lo, hi, allow_nan=False, allow_infinity=False))
        return float(self.rng.uniform(lo, hi))

    def choice(self, seq: Sequence[Any]) -> Any:
        if self.data is not None:
            return self.data.draw(st.sampled_from(list(seq)))
        return seq[int(self.rng.integers(len(seq)))]

    def flag(self, p: float) -> bool:
        if self.data is not None:
            return self.data.draw(st.booleans()) if p > 0 else False
        return bool(self.rng.random() < p)


def _rotation(a: float, b: float, c: float) -> torch.Tensor:
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    Rz = torch.tensor([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    Ry = torch.tensor([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]], dtype=torch.float64)
    Rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, cc, -sc], [0.0, sc, cc]], dtype=torch.float64)
    return Rz @ Ry @ Rx


def _cap_scales(means: torch.Tensor, scales: torch.Tensor, V: torch.Tensor, K: torch.Tensor, near: float,
                dtype: torch.dtype) -> None:
    """Shrink (in place) each point's scales into the documented domain for every camera: a bound
    ``f·s·(1+|x/z|+|y/z|)/z`` of the screen std-dev <= SIGMA_PX_MAX for points inside [near, far],
    ``f·s·(1+|x|+|y|)`` <= CULLED_FS_MAX for culled ones (project() uses z := 1 for them)."""
    fmax = float(K[0, 0].abs().clamp_min(K[1, 1].abs())) + float(K[0, 1].abs())
    for b in range(V.shape[0]):
        q = means @ V[b, :3, :3].T + V[b, :3, 3]
        z = q[:, 2]
        inside = (z >= near) & (z <= FAR)
        zs = torch.where(inside, z, torch.ones_like(z))
        lateral = 1.0 + (q[:, 0] / zs).abs() + (q[:, 1] / zs).abs()
        bound = torch.where(inside, SIGMA_PX_MAX[dtype] * zs, torch.full_like(z, CULLED_FS_MAX[dtype]))
        factor = (bound / (fmax * scales[:, 0] * lateral)).clamp(max=1.0)
        scales.mul_(factor[:, None])


def draw_case(draw: Draw, max_points: int = 10, max_size: int = 10) -> dict[str, Any]:
    """A random scene, cameras and op settings inside the documented domain (see the module docstring).

    Returns a dict with the op's positional tensors under their names, ``width``/``height`` and the
    keyword settings under ``kw``.
    """
    dtype = draw.choice((torch.float32, torch.float64))
    N = draw.integer(0, max_points)
    B = draw.integer(1, 2)
    W, H = draw.integer(1, max_size), draw.integer(1, max_size)
    C = draw.choice((1, 3))
    # intrinsics: focal over five decades, principal point anywhere near the image, optional skew
    f = 10.0 ** draw.uniform(-1.0, 4.0)
    fy = f * draw.choice((1.0, 10.0 ** draw.uniform(-0.3, 0.3)))
    skew = draw.choice((0.0, 0.0, draw.uniform(-0.1, 0.1) * f))
    cx, cy = draw.uniform(-0.5, 1.5) * W, draw.uniform(-0.5, 1.5) * H
    K = torch.tensor([[f, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    # camera-space points of camera 0: depths over nine decades, pixels partly off screen
    z0 = 10.0 ** draw.uniform(-3.0, 6.0)
    near = min(0.01, 0.01 * z0)
    q = torch.zeros(N, 3, dtype=torch.float64)
    normals_c = torch.zeros(N, 3, dtype=torch.float64)
    scales = torch.zeros(N, 2, dtype=torch.float64)
    opac = torch.zeros(N, dtype=torch.float64)
    lo, hi = math.log10(SIGMA_PX_MIN[dtype]), math.log10(SIGMA_PX_MAX[dtype])
    for k in range(N):
        kind = draw.choice(("normal",) * 6 + ("behind", "near", "far"))
        z = z0 * 10.0 ** draw.uniform(-0.5, 0.5)
        if kind == "behind":
            z = -z
        elif kind == "near":
            z = near
        elif kind == "far":
            z = FAR * draw.choice((0.5, 2.0))
        u, v = draw.uniform(-0.5, 1.5) * W, draw.uniform(-0.5, 1.5) * H
        y = (v - cy) / fy
        q[k] = torch.tensor([((u - cx) - skew * y) / f * abs(z), y * abs(z), z], dtype=torch.float64)
        sigma = 10.0 ** draw.uniform(lo, hi)
        scales[k, 0] = sigma * abs(z) / f
        scales[k, 1] = scales[k, 0] * 10.0 ** draw.uniform(-2.0, 0.0)
        n = torch.tensor([draw.uniform(-1, 1), draw.uniform(-1, 1), -draw.uniform(0.05, 1.0)], dtype=torch.float64)
        tilt = draw.choice(("any", "any", "edge_on", "nearly_edge_on"))
        if tilt != "any":  # normal perpendicular (or 1e-6 away from perpendicular) to the viewing ray
            n = torch.linalg.cross(q[k], n)
            if float(n.norm()) == 0.0:
                n = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
            n = n / n.norm()
            if tilt == "nearly_edge_on":
                n = n + 1e-6 * q[k] / q[k].norm()
        normals_c[k] = n
        opac[k] = draw.choice((0.0, 1e-30, 1.0, draw.uniform(0.0, 1.0), draw.uniform(0.0, 1.0)))
    if N > 1 and draw.flag(0.2):  # coincident points
        q[1:], normals_c[1:], scales[1:] = q[:1], normals_c[:1], scales[:1]
    # camera 0 pose, the world offset, and a slightly moved camera 1
    R0 = _rotation(draw.uniform(-3.2, 3.2), draw.uniform(-1.5, 1.5), draw.uniform(-3.2, 3.2))
    t0 = torch.tensor([draw.uniform(-1, 1), draw.uniform(-1, 1), draw.uniform(-1, 1)], dtype=torch.float64) * z0
    offset = draw.choice(OFFSETS)
    means = (q - t0) @ R0 + offset
    normals = normals_c @ R0
    Rs, ts = [R0], [t0]
    if B == 2:
        dR = _rotation(draw.uniform(-0.1, 0.1), draw.uniform(-0.1, 0.1), draw.uniform(-0.1, 0.1))
        Rs.append(dR @ R0)
        ts.append(dR @ t0 + 0.05 * z0 * torch.tensor([draw.uniform(-1, 1), draw.uniform(-1, 1), 0.0],
                                                     dtype=torch.float64))
    V = torch.zeros(B, 4, 4, dtype=torch.float64)
    for b in range(B):
        V[b, :3, :3] = Rs[b]
        V[b, :3, 3] = ts[b] - Rs[b] @ torch.full((3,), offset, dtype=torch.float64)
        V[b, 3, 3] = 1.0
    _cap_scales(means, scales, V, K, near, dtype)
    feats = torch.tensor([[draw.uniform(-3, 3) for _ in range(C)] for _ in range(N)], dtype=torch.float64)
    feats = feats.reshape(N, C)
    bg = torch.tensor([draw.uniform(-1, 2) for _ in range(C)], dtype=torch.float64)
    m = draw.integer(1, 6)
    kw = dict(samples=m, eps=draw.choice((1.0, 0.1, 0.01, 1e-3)), estimator=draw.choice(ESTIMATORS),
              composite=draw.choice(COMPOSITES), near=near, lowpass=draw.choice(LOWPASS[dtype]),
              seed=draw.integer(0, 2**31), hermite_order=draw.choice((0, 4, 8, 16)),
              hermite_tol=draw.choice((1e-3, 1e-2, 0.5)))
    tensors = dict(means=means, normals=normals, scales=scales, opacities=opac, features=feats, viewmats=V,
                   Ks=K.expand(B, 3, 3).clone(), background=bg)
    case = {k: v.to(dtype) for k, v in tensors.items()}
    case.update(width=W, height=H, kw=kw, dtype=dtype)
    return case


LEAVES = ("means", "normals", "scales", "opacities", "features", "viewmats", "Ks", "background")


def check_case(case: dict[str, Any]) -> list[str]:
    """Run the op forward and backward on ``case``; returns the violated properties (empty if none)."""
    leaves = {k: case[k].clone().requires_grad_() for k in LEAVES}
    W, H, kw = case["width"], case["height"], case["kw"]
    out = splat(leaves["means"], leaves["normals"], leaves["scales"], leaves["opacities"], leaves["features"],
                leaves["viewmats"], leaves["Ks"], W, H, background=leaves["background"], **kw)
    bad: list[str] = []
    for name in ("image", "alpha", "depth", "total", "probs"):
        if not bool(torch.isfinite(getattr(out, name)).all()):
            bad.append(f"{name} has NaN/Inf")
    if kw["composite"] == "alpha" and not bool(((out.alpha >= 0) & (out.alpha <= 1)).all()):
        bad.append(f"alpha outside [0,1]: [{float(out.alpha.min())}, {float(out.alpha.max())}]")
    N = case["means"].shape[0]
    idx, probs = out.indices, out.probs
    filled = idx >= 0
    if not bool(((idx >= -1) & (idx < N)).all()):
        bad.append("index out of range")
    if filled.shape[-1] > 1 and bool((~filled[..., :-1] & filled[..., 1:]).any()):
        bad.append("filled slot after an empty one")
    srt = torch.sort(idx, dim=-1).values
    if bool(((srt[..., 1:] == srt[..., :-1]) & (srt[..., 1:] >= 0)).any()):
        bad.append("duplicate index in a pixel")
    if not bool(((probs[filled] > 0) & (probs[filled] <= 1)).all()):
        bad.append("probability of a sampled point outside (0, 1]")
    if not bool((probs[~filled] == 0).all()):
        bad.append("non-zero probability in an empty slot")
    with torch.no_grad():
        proj = project(case["means"], case["normals"], case["scales"], case["opacities"], case["viewmats"],
                       case["Ks"], near=kw["near"], far=FAR, lowpass=kw["lowpass"])
        B = idx.shape[0]
        cams = torch.arange(B)[:, None, None, None].expand_as(idx)
        if bool(filled.any()) and not bool((proj.amps[cams[filled], idx[filled].long()] > 0).all()):
            bad.append("a culled or zero-amplitude point was sampled")
        if kw["composite"] == "alpha":
            # the compositing weights w_k = alpha_k T_k of each pixel sum to 1 - T_end <= 1
            ones = case["features"].new_ones(N, 1)
            wsum = composite_sample(proj, ones, case["Ks"], idx, probs, composite="alpha")[0]
            tol = 4 * torch.finfo(case["dtype"]).eps
            if not bool((wsum <= 1 + tol).all()) or not bool((wsum >= 0).all()):
                bad.append(f"compositing weights sum outside [0, 1]: max {float(wsum.max())}")
    g = torch.Generator().manual_seed(0)
    wi, wa, wd = (torch.randn(t.shape, generator=g, dtype=torch.float64).to(case["dtype"])
                  for t in (out.image, out.alpha, out.depth))
    scale_d = 1.0 / max(1.0, float(out.depth.detach().abs().max()))
    loss = (out.image * wi).sum() + (out.alpha * wa).sum() + (out.depth * wd).sum() * scale_d
    grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
    for name, gr in zip(LEAVES, grads):
        if gr is not None and not bool(torch.isfinite(gr).all()):
            bad.append(f"gradient of {name} has NaN/Inf")
    return bad


def describe(case: dict[str, Any]) -> str:
    """Short text of a case for failure reports."""
    sc = case["scales"]
    return (f"{case['dtype']} N={case['means'].shape[0]} B={case['viewmats'].shape[0]} {case['width']}x"
            f"{case['height']} scales=[{float(sc.min()) if sc.numel() else 0:.3g}, "
            f"{float(sc.max()) if sc.numel() else 0:.3g}] |means|max="
            f"{float(case['means'].abs().max()) if sc.numel() else 0:.3g} kw={case['kw']}")


@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(st.data())
def test_op_properties_over_the_documented_domain(data):
    case = draw_case(Draw(data=data))
    bad = check_case(case)
    assert not bad, f"{bad} for {describe(case)}"


# ------------------------------------------------------------------------------------------ determinism
def _grads(deterministic: bool, threads: int, dtype=torch.float32, estimator="ht", composite="alpha",
           N=400, W=40, H=30, B=2, samples=12):
    sc = make_scene(N, 3, dtype=dtype, scale=(0.02, 0.08))
    V, K = make_cameras(B, W, H, dtype=dtype)
    leaves = [t.clone().requires_grad_() for t in (sc["means"], sc["normals"], sc["scales"], sc["opacities"],
                                                   sc["features"], V)]
    bg = torch.full((3,), 0.3, dtype=dtype, requires_grad=True)
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        out = splat(*leaves, K, W, H, samples=samples, estimator=estimator, composite=composite, background=bg,
                    seed=5, deterministic=deterministic)
        g = torch.Generator().manual_seed(1)
        wi, wa, wd = (torch.randn(t.shape, generator=g, dtype=torch.float64).to(dtype)
                      for t in (out.image, out.alpha, out.depth))
        loss = (out.image * wi).sum() + (out.alpha * wa).sum() + (out.depth * wd).sum()
        return torch.autograd.grad(loss, leaves + [bg])
    finally:
        torch.set_num_threads(prev)


@pytest.mark.parametrize("estimator,composite", [("ht", "alpha"), ("paper", "additive"), ("sampled", "alpha")])
def test_deterministic_backward_is_bitwise_reproducible_across_runs_and_threads(estimator, composite):
    ref = _grads(True, 2, estimator=estimator, composite=composite)
    for threads in (2, 1, 2):
        got = _grads(True, threads, estimator=estimator, composite=composite)
        for name, a, b in zip(LEAVES, ref, got):
            assert torch.equal(a, b), f"{name}: gradients differ bitwise (threads={threads})"


def _capabilities() -> list[str]:
    """ATen CPU capabilities this CPU can run, from ``default`` up to the one ATen picks by itself (x86-64:
    ``default``, ``avx2``, ``avx512``; forcing one the CPU lacks would crash with an illegal instruction).
    Asked of a child process without ``ATEN_CPU_CAPABILITY``, so that a forced level in this process (the
    suite run under ``ATEN_CPU_CAPABILITY=default``) does not hide the CPU's own."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "ATEN_CPU_CAPABILITY"}
    top = subprocess.run([sys.executable, "-c", "import torch; print(torch.backends.cpu.get_cpu_capability())"],
                         env=env, capture_output=True, text=True, check=True).stdout.strip()
    levels = ["DEFAULT", "AVX2", "AVX512"]
    return [c.lower() for c in (levels[: levels.index(top) + 1] if top in levels else ["DEFAULT", top])]


def test_op_is_bitwise_identical_across_threads_and_cpu_capabilities(tmp_path):
    """The documented promise (docs/op.md §4): with ``deterministic=True`` the forward (samples, π, image,
    alpha, depth) and every gradient are bitwise identical for 1, 2 and 3 threads and under each ATen CPU
    capability of this CPU (vector width: the projection uses element-wise arithmetic only, and the
    native code is compiled once, without ``-march=native``)."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    sc = make_scene(400, 3, dtype=torch.float32, scale=(0.02, 0.08))
    V, K = make_cameras(2, 40, 30, dtype=torch.float32)
    g = torch.Generator().manual_seed(1)
    case = {**sc, "viewmats": V, "Ks": K, "width": 40, "height": 30,
            "background": torch.full((3,), 0.3), **{k: torch.randn(shape, generator=g)
                                                    for k, shape in (("wi", (2, 30, 40, 3)), ("wa", (2, 30, 40, 1)),
                                                                     ("wd", (2, 30, 40, 1)))}}
    torch.save(case, tmp_path / "case.pt")
    root = Path(__file__).resolve().parents[1]
    runs = {}
    for cap in _capabilities():
        env = dict(os.environ, ATEN_CPU_CAPABILITY=cap, PYTHONPATH=str(root))
        r = subprocess.run([sys.executable, "-m", "tests.determinism_probe", str(tmp_path / "case.pt")], cwd=root,
                           env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        got = json.loads(r.stdout.strip().splitlines()[-1])
        assert got["capability"].lower() == cap, got["capability"]
        runs[cap] = got["digests"]
    assert len(runs) >= 2  # default and at least the CPU's own vector width (x86-64: avx2 or avx512)
    ref_cap = next(iter(runs))
    for cap, digests in runs.items():
        for key, fields in digests.items():
            setting = key.split("/", 1)[1]
            want = runs[ref_cap][f"1/{setting}"]
            diff = [f for f in fields if fields[f] != want[f]]
            assert not diff, f"{diff} differ: {cap} at {key} vs {ref_cap} at 1 thread"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("estimator,composite", [("ht", "alpha"), ("paper", "alpha"), ("sampled", "additive"),
                                                 ("ht", "additive")])
def test_scatter_backward_matches_deterministic(dtype, estimator, composite):
    ref = _grads(True, 2, dtype=dtype, estimator=estimator, composite=composite)
    got = _grads(False, 2, dtype=dtype, estimator=estimator, composite=composite)
    eps = torch.finfo(dtype).eps
    for name, a, b in zip(LEAVES, ref, got):
        # both sum the same terms in a different order: the difference is rounding, bounded by
        # (number of terms per point) * eps * (sum of magnitudes); we use the max magnitude with a
        # generous term count of 1e3.
        tol = 1e3 * eps * float(a.abs().max())
        assert float((a - b).abs().max()) <= tol, f"{name}: {float((a - b).abs().max())} > {tol}"


@pytest.mark.parametrize("deterministic", [True, False])
def test_flag_selects_the_backward_path(deterministic, monkeypatch):
    """deterministic=True runs the two-pass gather and never the scatter; False the reverse (CPU)."""
    import dataclasses

    import nsplat.ops.library as lib

    calls: list[str] = []

    class Spy:
        def __init__(self, mod):
            self.mod = mod

        def __getattr__(self, name):
            calls.append(name)
            return getattr(self.mod, name)

    real = lib.native
    monkeypatch.setattr(lib, "native", lambda kind: dataclasses.replace(real(kind), module=Spy(real(kind).module)))
    _grads(deterministic, 1, N=50, W=8, H=6, B=1)
    assert ("composite_backward_scatter" in calls) != deterministic
    assert ("composite_backward_points" in calls) == deterministic
    assert ("composite_backward_pixels" in calls) == deterministic


def test_deterministic_flag_is_validated_and_module_plumbs_it():
    from nsplat.ops import Splatter

    sc = make_scene(30, 0, dtype=torch.float32)
    V, K = make_cameras(1, 8, 8, dtype=torch.float32)
    args = (sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, 8, 8)
    with pytest.raises(TypeError, match="deterministic"):
        splat(*args, deterministic="yes")
    m = Splatter(samples=4, deterministic=False)
    assert m.deterministic is False
    feats = sc["features"].clone().requires_grad_()
    out = m(*args[:4], feats, *args[5:], seed=0)
    out.image.sum().backward()
    ref_feats = sc["features"].clone().requires_grad_()
    splat(*args[:4], ref_feats, *args[5:], samples=4, seed=0).image.sum().backward()
    assert torch.allclose(feats.grad, ref_feats.grad, rtol=1e-5, atol=1e-6)
