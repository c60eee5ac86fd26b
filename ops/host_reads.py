"""Counting the op's host reads and host-to-device copies (what blocks a GPU stream).

On a GPU, every read of tensor values by the host (``.item()``, ``bool(t)``, ``.cpu()``) waits for the stream, and
every tensor built from Python data on a device (``torch.tensor(..., device=...)``) is a copy from the host. The op
reads on purpose in two places of its Python code, both through :func:`host_read`: the value checks of a call
(``ops/value_checks.py``: the inputs' checks together, then the projection's hazards together), and once per call
in the CUDA sampler (the tile item offsets and the coefficient total; the trees' valid counts stay on the device),
counted by the native module (``host_reads()``, the CUDA module and its host emulation).

:func:`count_host_traffic` counts both kinds in a block and, through a dispatch mode, every other read or copy the
block's PyTorch code makes outside the custom ops: so a test on the CPU (the host emulation of the CUDA launch code)
can assert the reads a step would make on a GPU, and that nothing else would block.
"""
from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Iterator

import torch
from torch.utils._python_dispatch import TorchDispatchMode

__all__ = ["HostTraffic", "count_host_traffic", "host_read"]

_COUNTERS: list[HostTraffic] = []
#: ATen ops that read device values back to the host inside their CUDA kernels (output sizes or ranges that depend on
#: the data): invisible as ``_local_scalar_dense`` in a dispatch mode, so :class:`_Spy` names them. ``bincount`` reads
#: its input's min and max; the others size their outputs from the data.
SYNCING_OPS = frozenset({"bincount", "histc", "nonzero", "unique", "_unique", "_unique2", "unique_consecutive",
                         "unique_dim", "masked_select", "repeat_interleave", "argwhere"})
_INSIDE_READ = [0]  # > 0 while host_read copies (its copy is the counted read, not another one)


def host_read(t: torch.Tensor) -> torch.Tensor:
    """``t`` on the host: the op's one way to read tensor values (a synchronisation on a GPU), counted."""
    for c in _COUNTERS:
        c.reads += 1
    _INSIDE_READ[0] += 1
    try:
        return t.cpu()
    finally:
        _INSIDE_READ[0] -= 1


@dataclasses.dataclass
class HostTraffic:
    """What a :func:`count_host_traffic` block did.

    Attributes:
        reads: reads through :func:`host_read` (the value checks).
        native_reads: the native sampler's reads of sizes (the CUDA module's counter).
        other: every other blocking read or host-to-device copy the block's PyTorch code made, one line each
            (``aten`` op and devices): ``_local_scalar_dense`` (``item``, ``bool``), a copy between devices, a
            tensor built from Python data (``lift_fresh``: on a device, a copy from the host), or an op of
            :data:`SYNCING_OPS` (``bincount``, ``nonzero``, ...: their CUDA kernels read values back).
    """

    reads: int = 0
    native_reads: int = 0
    other: list[str] = dataclasses.field(default_factory=list)

    @property
    def total(self) -> int:
        """All reads: the counted ones and the others."""
        return self.reads + self.native_reads + len(self.other)


class _Spy(TorchDispatchMode):
    """Records the blocking reads and copies among the ops dispatched in its block (not inside custom ops)."""

    def __init__(self, traffic: HostTraffic) -> None:
        super().__init__()
        self.traffic = traffic

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN206 - dispatch protocol
        kwargs = kwargs or {}
        if _INSIDE_READ[0]:
            return func(*args, **kwargs)
        name = str(func.overloadpacket.__name__)
        if name in ("_local_scalar_dense", "lift_fresh", "lift_fresh_copy"):
            self.traffic.other.append(name)
        elif name in SYNCING_OPS:
            self.traffic.other.append(f"{name} (reads device values back on CUDA)")
        elif name in ("_to_copy", "copy_"):
            src = args[1] if name == "copy_" else args[0]
            dst = kwargs.get("device") if name == "_to_copy" else args[0].device
            if isinstance(src, torch.Tensor) and dst is not None and torch.device(dst) != src.device:
                self.traffic.other.append(f"{name} {src.device} -> {dst}")
        return func(*args, **kwargs)


@contextlib.contextmanager
def count_host_traffic(native_reads: Callable[[], int] | None = None) -> Iterator[HostTraffic]:
    """Count the host reads and copies of the block (see :class:`HostTraffic`). ``native_reads``: the native
    module's read counter (``module.host_reads``), sampled before and after the block."""
    traffic = HostTraffic()
    before = native_reads() if native_reads else 0
    _COUNTERS.append(traffic)
    try:
        with _Spy(traffic):
            yield traffic
    finally:
        _COUNTERS.remove(traffic)
        traffic.native_reads = (native_reads() - before) if native_reads else 0
