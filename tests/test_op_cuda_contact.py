"""What a first run on a GPU would hit at once, checked without one (issue 57): the host reads and host-to-device
copies of a step, the backward's slot sort past 2^31 slots, and the one-lane sampler at 400².

The reads are counted by :func:`nsplat.ops.host_reads.count_host_traffic` on the host emulation of the CUDA launch
code (``tests/test_op_cuda.py``, ``emulated``): the value checks' reads, the native sampler's one read of sizes,
and every other blocking read or copy a step's PyTorch code makes. On a GPU ``test_cuda_step_reads_back_three_times_
whatever_the_views`` (tests/test_op_cuda.py) counts the same three with torch's sync debug mode.
"""
from __future__ import annotations

import pytest
import torch

import nsplat.ops.library as library
from nsplat.ops import Splatter, project, sample
from nsplat.ops.host_reads import count_host_traffic, host_read
from nsplat.render.renderer import RenderConfig, render
from tests.conftest import make_cameras, make_scene
from tests.test_op_cuda import _assert_identical, _both, _emulate, assert_same_sample_law, emulated  # noqa: F401

PARAMS = ("means", "normals", "scales", "opacities", "features")


def test_host_traffic_counter_sees_reads_and_copies():
    """The hook fails when a step reads or copies: a tensor built from Python data, a bool of a tensor and a copy to
    another device are each recorded; a read through host_read is counted as one."""
    x = torch.ones(3)
    with count_host_traffic() as t:
        torch.tensor([0.0, 0.0, 0.0, 1.0])
        bool(x.any())
        x.to("meta")
        host_read(x)
    assert t.reads == 1 and t.native_reads == 0
    assert len(t.other) == 3 and t.other[0].startswith("lift_fresh") and t.other[1] == "_local_scalar_dense"
    assert "cpu -> meta" in t.other[2] and t.total == 4


@pytest.mark.parametrize("B", [1, 6])
def test_emulated_step_reads_back_three_times_whatever_the_views(emulated, monkeypatch, B):  # noqa: F811
    """A step through the gateway (default background from the config, one seed per view, B views in one call, L1,
    backward) reads back three times on the CUDA launch code: the inputs' value checks together, the projection's
    hazards together, the sampler's one size read (its trees' valid counts stay on the device). No other read or
    host-to-device copy."""
    sc = make_scene(600, 8, dtype=torch.float32, scale=(0.01, 0.05))
    ps = [sc[n].requires_grad_() for n in PARAMS]
    V, K = make_cameras(B, 24, 20, dtype=torch.float32)
    target = torch.rand(B, 20, 24, 3, generator=torch.Generator().manual_seed(1))
    cfg = RenderConfig(samples=8, background=(1.0, 0.5, 0.25))
    seeds = torch.arange(B) + 7
    _emulate(monkeypatch, emulated)
    with count_host_traffic(emulated.host_reads) as t:
        out = render(*ps, V, K, 24, 20, cfg, seed=seeds)
        (out.image - target).abs().mean().backward()
    assert (t.reads, t.native_reads, t.other) == (2, 1, [])
    assert all(p.grad is not None for p in ps)


def test_splatter_call_counter_stays_on_the_host():
    """Splatter's per-call seed counter stays on the host when the module moves (a counter on a GPU would make the
    sampler's read of the seed a synchronisation); it still saves and loads with the state dict."""
    splatter = Splatter(samples=4).to("meta")
    assert splatter.calls.device == torch.device("cpu")
    splatter.calls += 5
    other = Splatter(samples=4).to("meta")
    other.load_state_dict(splatter.state_dict())
    assert other.calls.device == torch.device("cpu") and int(other.calls) == 5


@pytest.mark.parametrize("chunk", [1, 5, 64, 839, 840])
def test_slot_sort_in_runs_equals_one_sort(chunk):
    """The backward's grouping of slots by point, sorted in runs of ``chunk`` slots (as past 2^31 slots), equals one
    stable sort of all of them, empty slots and points without slots included."""
    g = torch.Generator().manual_seed(3)
    idx = torch.randint(-1, 40, (2, 5, 7, 12), generator=g, dtype=torch.int32)
    idx[idx == 17] = -1  # a point without slots
    whole = library._entries_by_point_sorted(idx, 45)
    runs = library._entries_by_point_sorted(idx, 45, chunk=chunk)
    assert all(torch.equal(a, b) for a, b in zip(whole, runs))


def test_emulated_backward_with_a_small_sort_run_equals_cpu(emulated, monkeypatch):  # noqa: F811
    """The CUDA launch code's deterministic backward with the slot sort cut into runs of 1000 slots (of 14 400) gives
    the CPU backend's bits."""
    monkeypatch.setattr(library, "SORT_CHUNK", 1000)
    sc = make_scene(500, 4, C=3, scale=(0.02, 0.06))
    V, K = make_cameras(2, 24, 20)
    (got, ref, proj), composited = _both(emulated, monkeypatch, sc, V, K, 24, 20, samples=15, seed=4)
    assert 2 * 24 * 20 * 15 > 10 * 1000
    assert_same_sample_law(got, ref, 0.01, proj, 4)
    _assert_identical(*composited)


def test_emulated_one_lane_at_400(emulated, monkeypatch):  # noqa: F811
    """At 400² the sampler picks one lane per pixel (pixels x lanes within 2^18 threads), the path until now covered
    only by the 2048² GPU test: the CPU backend's SPS law, and the same bits as one lane set explicitly."""
    sc = make_scene(160, 9, C=3, scale=(0.01, 0.03))
    V, K = make_cameras(1, 400, 400)
    proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10, lowpass=1.0)
    kw = dict(samples=3, eps=0.01, seed=2)
    ref = sample(proj, K, 400, 400, **kw)
    monkeypatch.delenv("NSPLAT_CUDA_PIXEL_LANES", raising=False)
    _emulate(monkeypatch, emulated)
    got = sample(proj, K, 400, 400, **kw)
    monkeypatch.setenv("NSPLAT_CUDA_PIXEL_LANES", "1")
    one = sample(proj, K, 400, 400, **kw)
    monkeypatch.undo()
    assert all(torch.equal(a, b) for a, b in zip(got, one))
    assert int((got[0] >= 0).any(-1).sum()) > 20000, "the scene is meant to cover much of the image"
    assert_same_sample_law(got, ref, 0.01, proj, 2)



def test_gpu_targets_table(tmp_path):
    """.ci/gpu_check.sh's last table: the measured values against the targets, a missing input "not measured"."""
    import json

    from benchmarks.targets import evaluate, gsplat_ratio, psnr_within, read, step_ms, table

    lego = {"rows": [{"resolution": 200, "views": 1, "step_ms": 7.5}, {"resolution": 200, "views": 8, "step_ms": 24.0},
                     {"resolution": 400, "views": 1, "step_ms": 3.0}]}
    (tmp_path / "lego.json").write_text(json.dumps(lego))
    curve = {"curve": [[60.0, 30.0], [170.0, 32.7], [200.0, 33.5]]}
    op = {"gsplat_2dgs": {"rows": [{"nsplat_over_gsplat": 2.0}, {"nsplat_over_gsplat": 3.5}]}}
    lego = read(tmp_path / "lego.json")
    rows = evaluate([step_ms(lego, 1), step_ms(lego, 8), psnr_within(curve, 180.0), 21.0,
                     gsplat_ratio(read(tmp_path / "absent.json"))])
    assert [(r["measured"], r["met"]) for r in rows] == [(7.5, True), (24.0, False), (32.7, True), (21.0, False),
                                                          (None, None)]
    assert gsplat_ratio(op) == 3.5 and step_ms(None, 1) is None
    assert "not measured" in table(rows) and "| NO |" in table(rows)
