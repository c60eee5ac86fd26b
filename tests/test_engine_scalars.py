"""The engine copies a step's scalars to the host only when it logs them: a GPU step need not wait for its own
results (issue: no host synchronisation inside a training step). On the CPU the copy is observed through a
0-dim tensor subclass that counts its conversions to a Python number."""
from __future__ import annotations

import torch
from torch import nn

from nsplat.run import distributed
from nsplat.run.engine import Engine, LogConfig, Trainables


class Counted(torch.Tensor):
    """A 0-dim tensor that counts how often it becomes a Python number (``float``/``item``), as a CUDA tensor's
    device-to-host copy would."""

    conversions = 0

    def __float__(self) -> float:
        Counted.conversions += 1
        return super().__float__()

    def item(self):  # noqa: ANN201
        Counted.conversions += 1
        return super().item()


def test_scalars_reach_the_host_only_when_logged(tmp_path):
    Counted.conversions = 0
    seen = []

    def step(k: int) -> dict:
        seen.append(k)
        return {"loss": torch.tensor(float(k)).as_subclass(Counted)}

    t = Trainables(modules={"m": nn.Linear(1, 1)})
    engine = Engine(tmp_path, LogConfig(every=5, images=0, validate=0, checkpoint=0, progress=False), 12)
    out = engine.train(t, step)
    assert seen == list(range(12))
    # logged after steps 5, 10 and the last (12): one conversion each; the returned scalars are the last log's
    assert Counted.conversions == 3
    assert out == {"loss": 11.0} and type(out["loss"]) is float


def test_reduced_scalars_stay_tensors_without_a_group():
    loss = torch.tensor(2.5, dtype=torch.float64)
    out = distributed.all_reduce_scalars({"train/loss": loss, "lr": 0.1})
    assert out["train/loss"] is loss and out["lr"] == 0.1


def _busy_step(k: int) -> dict:
    """A step that spends measurable CPU time (a few ms) and fails at step 3 of a first segment."""
    if k == 3 and _busy_step.fail:
        raise KeyboardInterrupt
    x = torch.ones(200_000, dtype=torch.float64)
    for _ in range(20):
        x = x.sqrt() + 1.0
    return {"loss": float(x[0])}


def _segment(run_dir, payload=None) -> Trainables:
    t = Trainables(modules={"m": nn.Linear(1, 1)})
    engine = Engine(run_dir, LogConfig(every=1, images=0, validate=0, checkpoint=1, progress=False), 6)
    start = engine.resume(t, payload)
    try:
        engine.train(t, _busy_step, start=start)
    except KeyboardInterrupt:
        pass
    return t


def test_step_times_accumulate_over_the_segments_of_a_resumed_run(tmp_path):
    from nsplat.run.checkpoint import load_checkpoint

    _busy_step.fail = True
    first = _segment(tmp_path / "run")  # killed in step 3: the checkpoint after step 3 holds steps 0-2
    saved = load_checkpoint(tmp_path / "run", map_location="cpu")
    assert saved["step"] == 3 and saved["extra"]["cpu_since"] == 0
    assert 0 < saved["extra"]["cpu_seconds"] and 0 < saved["extra"]["seconds"]
    _busy_step.fail = False
    resumed = _segment(tmp_path / "run", saved)
    assert resumed.extra["cpu_since"] == 0
    # steps 3-5 add to the first segment's totals (and the killed step 3 of the first segment is not counted)
    assert resumed.extra["cpu_seconds"] > saved["extra"]["cpu_seconds"]
    assert resumed.extra["seconds"] > saved["extra"]["seconds"]
    assert first.extra["cpu_seconds"] == saved["extra"]["cpu_seconds"]

    # a checkpoint written before CPU time was counted: counting starts at the resumed step
    old = load_checkpoint(tmp_path / "run", map_location="cpu")
    old["step"] = 3
    for key in ("cpu_seconds", "cpu_since"):
        del old["extra"][key]
    late = _segment(tmp_path / "late", old)
    assert late.extra["cpu_since"] == 3 and late.extra["cpu_seconds"] > 0
