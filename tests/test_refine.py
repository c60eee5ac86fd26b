"""Task ``refine``: exact resume (N steps in one go == N/2 steps, then resume for N/2 more), with the
warm-up and the joint or alternating schedule, the coverage mask, the outlier filter (pruning) and
the learnable focal exercised on a tiny room; and that refinement reduces the pose error."""
import dataclasses
import json

import pytest
import torch

from nsplat.config import load_config, read_yaml
from nsplat.data.paths import config_dir
from nsplat.render.renderer import RenderConfig
from nsplat.run.checkpoint import load_checkpoint
from nsplat.run.context import RunContext
from nsplat.run.engine import LogConfig
from nsplat.scene import SceneConfig
from nsplat.tasks import refine
from nsplat.tasks.refine import commands


def _cfg(tmp_path, steps: int, schedule: str) -> refine.Config:
    cfg = refine.Config()
    cfg.scene = SceneConfig(learn=["means", "normals", "features", "opacities"], opacity=None)
    cfg.render = RenderConfig(near=0.3, background=[0.0, 0.0, 0.0])
    cfg.data.cache_dir = str(tmp_path / "cache")
    cfg.data.room = dataclasses.replace(cfg.data.room, width=20, height=15, frames=3, supersample=1,
                                        keyframe_stride=1, pixel_stride=2)
    cfg.render.samples = 8
    cfg.poses.learn_focal = True
    cfg.coverage_mask = 0.5
    cfg.optim.steps = steps
    cfg.optim.batch = 2
    cfg.optim.warmup = 2
    cfg.optim.schedule = schedule
    cfg.optim.alternate_every = 1
    cfg.optim.decay_every = 3
    cfg.filter = dataclasses.replace(cfg.filter, start=2, every=2, p_value=0.2)  # prunes in this run
    cfg.log = LogConfig(every=1, images=0, validate=0, checkpoint=2)
    return cfg


def _run(cfg, run_dir, resume, monkeypatch, losses):
    orig = commands.masked_l1

    def record(img, ref, mask):
        loss = orig(img, ref, mask)
        losses.append(float(loss.detach()))
        return loss

    monkeypatch.setattr(commands, "masked_l1", record)
    ctx = RunContext(run_dir=run_dir, device=torch.device("cpu"), seed=3, resume=resume)
    out = refine.run(cfg, ctx)
    monkeypatch.setattr(commands, "masked_l1", orig)
    return out


@pytest.mark.parametrize("schedule", ["joint", "alternating"])
def test_resume_is_exact(tmp_path, monkeypatch, schedule):
    torch.set_num_threads(1)
    n = 6
    once, split = [], []
    a, b = tmp_path / "once", tmp_path / "split"
    a.mkdir(), b.mkdir()
    final_a = _run(_cfg(tmp_path, n, schedule), a, False, monkeypatch, once)
    _run(_cfg(tmp_path, n // 2, schedule), b, False, monkeypatch, split)
    final_b = _run(_cfg(tmp_path, n, schedule), b, True, monkeypatch, split)
    assert len(once) == len(split) == n
    assert once == split  # bitwise equal losses, step by step
    ck_a, ck_b = load_checkpoint(a), load_checkpoint(b)
    assert ck_a["step"] == ck_b["step"] == n
    points = [ck["modules"]["model"]["scene._means"].shape[0] for ck in (ck_a, ck_b)]
    assert points[0] == points[1]
    assert final_a["removed"] > 0 and final_a["removed"] == final_b["removed"]  # the filter pruned points
    for k, v in ck_a["modules"]["model"].items():
        assert torch.equal(v, ck_b["modules"]["model"][k]), k
    for name in ck_a["optimizers"]:
        sa, sb = ck_a["optimizers"][name]["state"], ck_b["optimizers"][name]["state"]
        assert sa.keys() == sb.keys()
        for i in sa:
            for k in sa[i]:
                assert torch.equal(torch.as_tensor(sa[i][k]), torch.as_tensor(sb[i][k])), (name, i, k)
    twist = ck_a["modules"]["model"]["cameras.twist"]
    assert twist.abs().sum() > 0  # the poses moved
    for key in ("rot_deg", "trans", "psnr", "ssim", "points"):
        assert final_a[key] == final_b[key], key


def test_refinement_reduces_the_pose_error(tmp_path):
    """Joint refinement of poses, points and SH shading on a small room (6 frames at 64×48, every pose perturbed by
    2° and 8 cm, the noisy SLAM-like cloud of configs/refine_room.yaml, 150 steps, no outlier filter): the mean
    rotation error falls from 2.000° to 0.654° (÷3.1) and the translation error from 0.080 to 0.032 (÷2.5) as
    measured; asserted: at least ÷2.2 and ÷1.7."""
    torch.set_num_threads(1)
    cfg = load_config(refine.Config, read_yaml(config_dir() / "refine_room.yaml"), [
        "data.room.width=64", "data.room.height=48", "data.room.frames=6", "data.room.supersample=1",
        f"data.cache_dir={tmp_path / 'cache'}", "optim.steps=150", "optim.decay_every=0", "filter.enabled=false",
        "render.samples=16", "log.every=1000", "log.images=0", "log.checkpoint=0"])
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    final = refine.run(cfg, RunContext(run_dir=run_dir, device=torch.device("cpu"), seed=0, resume=False))
    initial = json.loads((run_dir / "metrics_initial.json").read_text())
    assert initial["rot_deg"] == pytest.approx(2.0, abs=1e-6) and initial["trans"] == pytest.approx(0.08, abs=1e-6)
    assert final["rot_deg"] < initial["rot_deg"] / 2.2
    assert final["trans"] < initial["trans"] / 1.7
