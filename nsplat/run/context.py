"""The run context handed to tasks, and the rules that make a run folder belong to one run.

A run folder belongs to one run:

* starting a run in a folder that already holds files needs ``--resume`` (continue that run) or
  ``--overwrite`` (delete its contents first); otherwise :func:`check_run_folder` refuses;
* while a run is alive it holds an advisory ``fcntl.flock`` on ``<run>/.lock`` (the file holds the
  holder's pid); a second process on the same folder is refused with that pid. The kernel releases the
  lock when the holder exits or dies, so a stale lock file of a dead process is simply re-locked;
* ``--resume`` with overrides that change the run's ``config.yaml`` is refused before anything is written;
* a run that completed leaves ``<run>/finished.json`` (:func:`mark_finished`); ``--resume`` of it changes
  nothing and says so (:func:`finished_at`).
"""
from __future__ import annotations

import dataclasses
import errno
import fcntl
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

import torch

#: Name of the lock file inside a run folder (ignored when deciding whether a folder is empty).
LOCK_NAME = ".lock"
#: Written when a run's ``train`` command completed.
FINISHED_NAME = "finished.json"


class RunFolderError(RuntimeError):
    """The run folder cannot be used as asked (not empty, in use, incompatible resume)."""


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


def folder_contents(run_dir: Path) -> list[Path]:
    """Entries of ``run_dir`` other than the lock file (empty when the folder does not exist)."""
    if not run_dir.is_dir():
        return []
    return sorted(p for p in run_dir.iterdir() if p.name != LOCK_NAME)


def check_run_folder(run_dir: Path, *, resume: bool, overwrite: bool) -> None:
    """Refuse to start a fresh run in a folder holding another run's files (read-only check).

    Raises:
        RunFolderError: ``run_dir`` exists and is not a folder; or it holds files and neither
            ``resume`` nor ``overwrite`` is set; or ``resume`` is set and it holds no ``config.yaml``.
    """
    if run_dir.exists() and not run_dir.is_dir():
        raise RunFolderError(f"run folder {run_dir} exists and is not a folder")
    if resume:
        if not (run_dir / "config.yaml").is_file():
            raise RunFolderError(f"--resume: {run_dir} holds no run to resume (no config.yaml)")
        return
    if folder_contents(run_dir) and not overwrite:
        raise RunFolderError(f"run folder {run_dir} is not empty (it holds a previous run); pass --resume to "
                             f"continue that run or --overwrite to delete it and start afresh")


def mark_finished(run_dir: Path) -> None:
    """Record that the run in ``run_dir`` completed (atomically: a partial file never exists)."""
    tmp = run_dir / f".{FINISHED_NAME}.tmp-{os.getpid()}"
    tmp.write_text(json.dumps({"finished": time.strftime("%Y-%m-%d %H:%M:%S")}) + "\n")
    os.replace(tmp, run_dir / FINISHED_NAME)


def finished_at(run_dir: Path) -> str | None:
    """When the run in ``run_dir`` completed (local time, as recorded), or ``None`` when it has not."""
    try:
        return str(json.loads((run_dir / FINISHED_NAME).read_text())["finished"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def config_differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested config dicts (sorted)."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        for key in sorted(set(old) | set(new), key=str):
            if key not in old or key not in new:
                out.append(f"{prefix}{key}")
            else:
                out.extend(config_differences(old[key], new[key], f"{prefix}{key}."))
        return out
    return [] if old == new else [prefix.rstrip(".")]


def lock_holder(run_dir: Path) -> int | None:
    """Pid of the live process holding ``run_dir``'s lock, or ``None`` when nobody holds it.

    Read-only: creates nothing (a missing lock file means the folder is free).
    """
    path = run_dir / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            return _read_pid(path)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _read_pid(path: Path) -> int:
    """The pid written in a lock file (0 when unreadable)."""
    try:
        return int(path.read_text().strip() or 0)
    except (OSError, ValueError):
        return 0


class RunLock:
    """Exclusive advisory lock on a run folder for the lifetime of a run (``with RunLock(dir): ...``).

    The lock file ``<run>/.lock`` holds the holder's pid. It is never deleted (deleting it would let two
    processes lock two different inodes); the kernel drops the lock when the holder exits or dies.
    """

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        self.fd: int | None = None

    def acquire(self) -> "RunLock":
        """Take the lock (the folder must exist); raises :class:`RunFolderError` naming the holder's pid."""
        path = self.run_dir / LOCK_NAME
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            raise RunFolderError(f"run folder {self.run_dir} is in use by process {_read_pid(path)} "
                                 f"(lock {path}); wait for it to finish or use another --run") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        """Drop the lock (idempotent)."""
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def clear_run_folder(run_dir: Path) -> None:
    """Delete everything in ``run_dir`` except the lock file (``--overwrite``, or a failed fresh start)."""
    for entry in folder_contents(run_dir):
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def pid_alive(pid: int) -> bool:
    """Whether a process with ``pid`` exists (signal 0; a process of another user counts as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
