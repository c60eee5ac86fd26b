"""Data-dependent argument checks run together, in one read back to the host.

A check of tensor *values* (NaN/Inf, signs and ranges, rigid viewmats, seeds, projection hazards) needs the
result on the host; on a GPU each such read is a synchronisation. Inside :func:`value_checks` the checks of
:func:`fail_if` are collected and read back together when the block ends (one read per device), so an op call
synchronises once for all of them instead of once per check. The first failing check in call order raises;
checks of types, shapes and settings (``ops/validation.py``) still raise at once, so they win over a value
check of an earlier argument. Outside a block :func:`fail_if` checks at once.
"""
from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator

import torch

from .host_reads import host_read

#: The pending value checks of the innermost :func:`value_checks` block (None: checks run at once).
_PENDING: contextvars.ContextVar[list[tuple[torch.Tensor, Callable[[], str]]] | None] = contextvars.ContextVar(
    "nsplat_pending_value_checks", default=None)


def fail_if(condition: torch.Tensor, message: Callable[[], str]) -> None:
    """Raise ``ValueError(message())`` when the 0-dim bool tensor ``condition`` is true: at once, or inside
    :func:`value_checks` when its block ends (``message`` is called only on failure, so it may read values)."""
    pending = _PENDING.get()
    if pending is None:
        if bool(condition):
            raise ValueError(message())
    else:
        pending.append((condition, message))


def value_checks() -> contextlib.AbstractContextManager[None]:
    """Run the :func:`fail_if` checks of the block together at its end (one host read per device; nested blocks
    join the outermost). The first failing check in call order raises. While ``torch.compile`` traces (the
    value checks are skipped then, ``ops/validation.py``) it is a null context."""
    return contextlib.nullcontext() if torch.compiler.is_compiling() else _collected()


@contextlib.contextmanager
def _collected() -> Iterator[None]:
    if _PENDING.get() is not None:
        yield
        return
    pending: list[tuple[torch.Tensor, Callable[[], str]]] = []
    token = _PENDING.set(pending)
    try:
        yield
    finally:
        _PENDING.reset(token)
    by_device: dict[torch.device, list[int]] = {}
    for i, (cond, _) in enumerate(pending):
        by_device.setdefault(cond.device, []).append(i)
    failed = [False] * len(pending)
    for rows in by_device.values():
        flags = host_read(torch.stack([pending[i][0].reshape(()) for i in rows])).tolist()  # the one host read
        for i, f in zip(rows, flags):
            failed[i] = bool(f)
    for (_, message), f in zip(pending, failed):
        if f:
            raise ValueError(message())
