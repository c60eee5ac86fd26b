"""The engine copies a step's scalars to the host only when it logs them: a GPU step need not wait for its own
results (issue: no host synchronisation inside a training step). On the CPU the copy is observed through a
0-dim tensor subclass that counts its conversions to a Python number."""
from __future__ import annotations

import torch
from torch import nn

from nsplat import distributed
from nsplat.engine import Engine, LogConfig, Trainables


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
