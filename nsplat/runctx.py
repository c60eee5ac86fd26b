"""The run context handed to tasks: run folder, device, seed, resume flag."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import torch


@dataclasses.dataclass
class RunContext:
    """Where a task writes (``run_dir``) and how it runs.

    Attributes:
        run_dir: folder for the resolved config, logs, checkpoints and outputs.
        device: torch device to run on.
        seed: global seed (also seeds the op's sampler).
        resume: continue from the last complete checkpoint in ``run_dir``.
    """

    run_dir: Path
    device: torch.device
    seed: int = 0
    resume: bool = False
