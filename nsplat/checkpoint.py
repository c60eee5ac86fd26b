"""Atomic checkpoints and exact resume.

A checkpoint is written to a temporary file in the same folder, flushed and fsync'ed, then renamed
over ``ckpt-<step>.pt`` (``os.replace`` is atomic on POSIX), and only then is ``latest`` updated the
same way. A process killed at any point leaves either the previous complete checkpoint or the new
one; partial temporaries are ignored and cleaned up by the next save.
"""
from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch


class CheckpointError(RuntimeError):
    """No usable checkpoint where one was expected, or a checkpoint file is corrupt."""


class NoCheckpoint(CheckpointError):
    """The run folder has no checkpoint yet (resuming may start from scratch; a corrupt one may not)."""


def rng_state() -> dict[str, Any]:
    """Capture Python, NumPy and torch (CPU and CUDA) RNG states."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore RNG states captured by :func:`rng_state`."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as fh:
        write(fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def save_checkpoint(run_dir: Path, step: int, state: dict[str, Any], keep: int = 2) -> Path:
    """Atomically write ``state`` (plus RNG states) as ``run_dir/checkpoints/ckpt-<step>.pt``.

    Keeps the newest ``keep`` checkpoints. Returns the checkpoint path.
    """
    folder = Path(run_dir) / "checkpoints"
    folder.mkdir(parents=True, exist_ok=True)
    for stale in folder.glob(".*.tmp-*"):
        stale.unlink(missing_ok=True)
    payload = dict(state, step=step, rng=rng_state())
    path = folder / f"ckpt-{step:08d}.pt"
    _atomic_write(path, lambda fh: torch.save(payload, fh))
    _atomic_write(folder / "latest", lambda fh: fh.write(path.name.encode()))
    for old in sorted(folder.glob("ckpt-*.pt"))[:-keep]:
        old.unlink(missing_ok=True)
    return path


def load_checkpoint(run_dir: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load the latest complete checkpoint of ``run_dir``.

    Raises :class:`NoCheckpoint` when there is none and :class:`CheckpointError` when the latest one
    is missing or unreadable (never silently falls back to an older or to no checkpoint).

    RNG states are restored. The returned dict has the saved state plus ``step``.
    """
    folder = Path(run_dir) / "checkpoints"
    latest = folder / "latest"
    if not latest.is_file():
        raise NoCheckpoint(f"no checkpoint to resume from in {folder}")
    path = folder / latest.read_text().strip()
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} named by {latest} does not exist")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a corrupt file
        raise CheckpointError(f"checkpoint {path} is unreadable: {exc}") from exc
    set_rng_state(payload.pop("rng"))
    return payload
