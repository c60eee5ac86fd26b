"""The CUDA paths real work takes (issue 68), each in the host emulation of the launch code and on a GPU.

* one, two and three threads per pixel at 400² (``NSPLAT_CUDA_PIXEL_LANES``): the CPU's sample law, and the CPU's
  sample composited through the CUDA launch code (bitwise in the emulation; within tests/float_parity.py's bounds on
  a GPU, where exp differs);
* more than 16 cameras (several camera groups), groups split by the scratch limit (``NSPLAT_CUDA_LANE_SCRATCH_BYTES``)
  and several key sorts (``NSPLAT_CUDA_SORT_CAMERAS``): every camera bitwise as that camera sampled alone;
* the backward's chunked slot sort without hidden synchronisations (``torch.bincount`` read min/max back on CUDA).

The scenes are small (few points, m <= 4) so that a 400² emulated sample takes seconds.
"""
from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch

import nsplat.ops.library as library
from nsplat.ops import composite_sample, project, sample
from nsplat.ops.host_reads import count_host_traffic
from tests.conftest import make_cameras, make_scene
from tests.float_parity import forward_tolerance
from tests.test_op_cuda import CUDA, _emulate, _proj_to, assert_same_sample_law, cuda_test, emulated, rel_err  # noqa: F401

#: A lane scratch limit that fits two cameras of _many_cameras (12x8 pixels: 6 tiles of 16 pixels, 2 lanes, m = 4):
#: each takes 96 (2 heaps of 4 x 12 bytes + 2 LaneStats of 48 + a merged heap of 48 + 8) = 23 808 bytes.
GROUP_OF_TWO = 50_000


def _scene_400(cameras: int = 1):
    """160 surfels over much of a 400² image (m = 3 leaves pruning and empty pixels)."""
    sc = make_scene(160, 9, C=3, scale=(0.01, 0.03))
    V, K = make_cameras(cameras, 400, 400)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    return sc, K, proj


def _composite(proj, features, K, idx, probs):
    """The image, alpha and depth of a fixed sample (no gradient)."""
    bg = torch.linspace(0.2, 0.7, features.shape[-1], dtype=features.dtype, device=features.device)
    return composite_sample(proj, features, K, idx, probs, background=bg), bg


def _one_camera(proj, b: int):
    return type(proj)(**{f.name: getattr(proj, f.name)[b:b + 1] for f in dataclasses.fields(proj)})


def _assert_cameras_sample_alone(proj, K, W, H, seeds, got):
    """Each camera of a call's sample ``got`` equals that camera sampled alone with its seed (bitwise)."""
    for b in range(len(seeds)):
        alone = sample(_one_camera(proj, b), K[b:b + 1], W, H, samples=4, eps=0.01, seed=int(seeds[b]))
        for a, c in zip(alone, got):
            assert torch.equal(a.cpu(), c[b:b + 1].cpu()), b


def _many_cameras(B: int, W: int, H: int):
    sc = make_scene(300, 5, C=3, scale=(0.01, 0.05))
    V, K = make_cameras(B, W, H)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    return proj, K, torch.arange(B) * 7 + 1


# --------------------------------------------------------------------------------------------------------
# Host emulation


@pytest.mark.parametrize("lanes", [1, 2, 3])
def test_emulated_lanes_at_400_draw_the_cpu_law_and_composite_its_bits(emulated, monkeypatch, lanes):  # noqa: F811
    """1, 2, 3 threads per pixel at 400²: the CPU's SPS law; the CPU's sample composited by the launch code gives the
    CPU's image, alpha and depth bitwise (same compiler, same exp)."""
    sc, K, proj = _scene_400()
    kw = dict(samples=3, eps=0.01, seed=2)
    ref = sample(proj, K, 400, 400, **kw)
    want, _ = _composite(proj, sc["features"], K, ref[0], ref[1])
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", str(lanes))
    _emulate(monkeypatch, emulated)
    got = sample(proj, K, 400, 400, **kw)
    out, _ = _composite(proj, sc["features"], K, ref[0], ref[1])
    monkeypatch.undo()
    assert int((got[0] >= 0).any(-1).sum()) > 20000, "the scene is meant to cover much of the image"
    assert_same_sample_law(got, ref, 0.01, proj, 2)
    for name, a, b in zip(("image", "alpha", "depth"), out, want):
        assert torch.equal(a, b), name


def test_emulated_many_cameras_split_groups_and_sorts_sample_as_one_call_per_view(emulated, monkeypatch):  # noqa: F811
    """20 cameras in one call with groups cut by the scratch limit (2 cameras a group) and key sorts of 3 cameras:
    every camera bitwise as that camera alone; the call reads sizes back to the host once, whatever its groups."""
    W, H = 12, 8
    proj, K, seeds = _many_cameras(20, W, H)
    _emulate(monkeypatch, emulated)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", "2")
    monkeypatch.setenv("NSPLAT_CUDA_SORT_CAMERAS", "3")
    monkeypatch.setenv("NSPLAT_CUDA_LANE_SCRATCH_BYTES", str(GROUP_OF_TWO))
    before, reads = emulated.launches(), emulated.host_reads()
    got = sample(proj, K, W, H, samples=4, eps=0.01, seed=seeds)
    split = emulated.launches() - before
    assert emulated.host_reads() - reads == 1
    monkeypatch.setenv("NSPLAT_CUDA_LANE_SCRATCH_BYTES", str(2**30))
    before = emulated.launches()
    whole = sample(proj, K, W, H, samples=4, eps=0.01, seed=seeds)
    assert split > emulated.launches() - before, "the scratch limit should split the cameras into more groups"
    assert all(torch.equal(a, b) for a, b in zip(got, whole))
    assert int((got[0] >= 0).sum()) > 0
    _assert_cameras_sample_alone(proj, K, W, H, seeds, got)
    monkeypatch.undo()


def test_emulated_settings_are_checked(emulated, monkeypatch):  # noqa: F811
    proj, K, _ = _many_cameras(2, 8, 8)
    _emulate(monkeypatch, emulated)
    monkeypatch.setenv("NSPLAT_CUDA_SORT_CAMERAS", "0")
    with pytest.raises(RuntimeError, match="NSPLAT_CUDA_SORT_CAMERAS must be a positive integer, got '0'"):
        sample(proj, K, 8, 8, samples=4)


def test_chunked_slot_sort_has_no_hidden_reads():
    """The backward's slot sort in runs (past 2^30 slots) reads nothing back: no bincount (which reads the keys' min
    and max on CUDA), item or copy; the counter sees such ops."""
    idx = torch.randint(-1, 40, (2, 5, 7, 12), generator=torch.Generator().manual_seed(3), dtype=torch.int32)
    with count_host_traffic() as t:
        library._entries_by_point_sorted(idx, 45, chunk=64)
    assert t.other == []
    with count_host_traffic() as t:
        torch.bincount(idx.reshape(-1).clamp_min(0))
    assert t.other == ["bincount (reads device values back on CUDA)"]


# --------------------------------------------------------------------------------------------------------
# On a GPU


@cuda_test
@pytest.mark.parametrize("lanes", [1, 2, 3])
def test_cuda_lanes_at_400_draw_the_cpu_law(monkeypatch, lanes):
    """1, 2, 3 threads per pixel at 400² on the GPU: the CPU's SPS law; the CPU's sample composited on the GPU within
    the float analysis's bound (its exp is the device's)."""
    sc, K, proj = _scene_400()
    kw = dict(samples=3, eps=0.01, seed=2)
    ref = sample(proj, K, 400, 400, **kw)
    want, bg = _composite(proj, sc["features"], K, ref[0], ref[1])
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", str(lanes))
    proj_g, K_g = _proj_to(proj, CUDA), K.to(CUDA)
    got = [t.cpu() for t in sample(proj_g, K_g, 400, 400, **kw)]
    out, _ = _composite(proj_g, sc["features"].to(CUDA), K_g, ref[0].to(CUDA), ref[1].to(CUDA))
    assert_same_sample_law(got, ref, 0.01, proj, 2)
    for name, a, b in zip(("image", "alpha", "depth"), out, want):
        tol = forward_tolerance(proj, sc["features"], bg, ref[0], ref[1], "alpha", b)
        assert rel_err(a, b) <= tol, (name, rel_err(a, b), tol)


@cuda_test
def test_cuda_many_cameras_split_groups_and_sorts_sample_as_one_call_per_view(monkeypatch):
    """20 cameras on the GPU, groups cut by the scratch limit and several key sorts: every camera bitwise as that
    camera alone, the CPU's law for all."""
    W, H = 12, 8
    proj, K, seeds = _many_cameras(20, W, H)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", "2")
    monkeypatch.setenv("NSPLAT_CUDA_SORT_CAMERAS", "3")
    monkeypatch.setenv("NSPLAT_CUDA_LANE_SCRATCH_BYTES", str(GROUP_OF_TWO))
    proj_g, K_g = _proj_to(proj, CUDA), K.to(CUDA)
    got = sample(proj_g, K_g, W, H, samples=4, eps=0.01, seed=seeds)
    _assert_cameras_sample_alone(proj_g, K_g, W, H, seeds, got)
    ref = sample(proj, K, W, H, samples=4, eps=0.01, seed=seeds)
    assert_same_sample_law([t.cpu() for t in got], ref, 0.01, proj, seeds)


@cuda_test
def test_cuda_chunked_slot_sort_does_not_synchronise(monkeypatch):
    """The backward with its slot sort in runs of 1000 slots: no synchronisation (torch's sync debug mode)."""
    idx = torch.randint(-1, 40, (2, 24, 20, 15), generator=torch.Generator().manual_seed(3), dtype=torch.int32)
    idx = idx.to(CUDA)
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            library._entries_by_point_sorted(idx, 45, chunk=1000)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    assert not [w for w in caught if "synchroniz" in str(w.message)]
