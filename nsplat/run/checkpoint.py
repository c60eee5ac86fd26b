"""Atomic checkpoints and exact resume.

A checkpoint is written to a temporary file in the same folder, flushed and fsync'ed, then renamed
over ``ckpt-<step>.pt`` (``os.replace`` is atomic on POSIX), and only then is ``latest`` updated the
same way. A process killed at any point leaves either the previous complete checkpoint or the new
one; partial temporaries are ignored and cleaned up by the next save, which removes only temporaries
whose writer (the pid in their name) is dead, never another live process's in-flight file.

Rotation keeps the newest ``keep`` checkpoints *of the current run*: only checkpoints with a step at or
below the one just written are candidates (a higher step cannot belong to this run's past), and the
file ``latest`` names is never removed.
"""
from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from nsplat.run.context import pid_alive


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


def temp_path(path: Path) -> Path:
    """The temporary file an atomic write of ``path`` goes through: ``.<name>.tmp-<pid>``."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Delete ``.*.tmp-<pid>`` files in ``folder`` whose writer is dead (or is this process, which has
    no write in flight when this is called); returns the removed paths."""
    removed = []
    for tmp in Path(folder).glob(".*.tmp-*"):
        pid_text = tmp.name.rsplit("-", 1)[-1]
        pid = int(pid_text) if pid_text.isdigit() else 0
        if pid == os.getpid() or not pid_alive(pid):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def atomic_write(path: Path, write: Callable[[Any], Any]) -> None:
    """Write ``path`` atomically: ``write(fh)`` into a pid-named temporary, fsync, rename, fsync the folder."""
    _atomic_write(Path(path), write)


def _atomic_write(path: Path, write) -> None:
    tmp = temp_path(path)
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
    remove_stale_temporaries(folder)
    payload = dict(state, step=step, rng=rng_state())
    path = folder / f"ckpt-{step:08d}.pt"
    _atomic_write(path, lambda fh: torch.save(payload, fh))
    _atomic_write(folder / "latest", lambda fh: fh.write(path.name.encode()))
    rotate_checkpoints(folder, step, keep)
    return path


def _step_of(path: Path) -> int | None:
    """The step in ``ckpt-<step>.pt`` (None for other names)."""
    digits = path.stem.removeprefix("ckpt-")
    return int(digits) if digits.isdigit() else None


def rotate_checkpoints(folder: Path, step: int, keep: int) -> list[Path]:
    """Remove all but the newest ``keep`` checkpoints with step <= ``step``; never the one ``latest``
    names nor any with a higher step. Returns the removed paths."""
    latest = folder / "latest"
    named = latest.read_text().strip() if latest.is_file() else None
    mine = sorted((s, p) for p in folder.glob("ckpt-*.pt") if (s := _step_of(p)) is not None and s <= step)
    removed = []
    for _, old in mine[:-max(keep, 1)]:
        if old.name != named:
            old.unlink(missing_ok=True)
            removed.append(old)
    return removed


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
