"""Data-parallel training over ``torch.distributed`` (``torchrun``; docs/distributed.md).

A run started by ``torchrun --nproc_per_node=P train.py ...`` has ``P`` ranks (processes); each renders
its share of every step's views and the gradients are summed across ranks with one all-reduce per
optimiser, so every rank applies the same update and holds the same model after every step. Rank 0
alone writes the run folder. Without torchrun (``WORLD_SIZE`` unset or 1) every function here is the
single-process identity: :func:`shard` is the whole range, reductions return their input.

* :func:`init_from_env` / :func:`shutdown` — the process group (gloo on CPU, NCCL on CUDA) with a timeout;
  :func:`communication_threads` — its threads still alive (none after :func:`shutdown`).
* :func:`rank`, :func:`world_size`, :func:`is_main` — who this process is.
* :func:`shard` — this rank's contiguous share of ``n`` global slots (views of a step).
* :func:`all_reduce_grads`, :func:`all_reduce_sum`, :func:`all_reduce_scalars`, :func:`broadcast_modules`,
  :func:`broadcast_object` — the collectives; any failure (a dead rank, the timeout) is raised as
  :class:`DistributedError` with a message naming the operation, the rank and the timeout.
"""
from __future__ import annotations

import datetime
import os
from typing import Any, Callable, Iterable, Mapping, TypeVar

import torch
import torch.distributed as dist
from torch import nn

#: Default seconds a rank waits in a collective for the others (``--dist-timeout``).
DEFAULT_TIMEOUT_S = 600.0

_timeout_s = DEFAULT_TIMEOUT_S
T = TypeVar("T")


class DistributedError(RuntimeError):
    """A collective failed: another rank died, or did not answer within the process-group timeout."""


def launched() -> bool:
    """Whether this process was started by ``torchrun`` with more than one process in the job."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def active() -> bool:
    """Whether a process group with more than one rank is initialised."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def rank() -> int:
    """This process's rank (0 without a process group)."""
    return dist.get_rank() if active() else 0


def world_size() -> int:
    """Number of ranks (1 without a process group)."""
    return dist.get_world_size() if active() else 1


def is_main() -> bool:
    """Whether this process writes the run folder (rank 0, or the only process)."""
    return rank() == 0


def local_device(device: torch.device) -> torch.device:
    """``device`` for this process: ``cuda`` becomes ``cuda:LOCAL_RANK`` under torchrun (one GPU per rank)."""
    if device.type == "cuda" and device.index is None and launched():
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def init_from_env(device: torch.device, timeout_s: float = DEFAULT_TIMEOUT_S) -> bool:
    """Join the process group that torchrun describes in the environment (``RANK``, ``WORLD_SIZE``,
    ``MASTER_ADDR``, ``MASTER_PORT``); returns whether one was joined (``False`` outside torchrun).

    Args:
        device: this rank's device (:func:`local_device`): NCCL for CUDA, gloo for CPU.
        timeout_s: seconds a collective waits for the other ranks before it fails (> 0).
    """
    global _timeout_s
    if timeout_s <= 0:
        raise ValueError(f"timeout_s: expected > 0 seconds, got {timeout_s}")
    if not launched():
        return False
    if not dist.is_available():
        raise DistributedError("torch.distributed is not available in this PyTorch build")
    _timeout_s = float(timeout_s)
    _import_group_capturing_modules()
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    try:
        dist.init_process_group(backend, init_method="env://", timeout=datetime.timedelta(seconds=timeout_s),
                                **({"device_id": device} if device.type == "cuda" else {}))
    except Exception as exc:  # noqa: BLE001 - rendezvous failures come in many types
        raise DistributedError(f"could not join the process group ({backend}, rank {os.environ.get('RANK')} of "
                               f"{os.environ.get('WORLD_SIZE')}): {_one_line(exc)}") from exc
    return True


def _import_group_capturing_modules() -> None:
    """Import, before the process group exists, the torch modules that bind the default group at import time.

    ``torch.distributed.fsdp`` evaluates ``dist.group.WORLD`` as a default argument when it is imported, and
    torch imports it lazily with ``torch._dynamo``, which the op's first call loads. Imported after
    :func:`init_from_env`, that hidden reference keeps the group alive through ``destroy_process_group``: its
    gloo threads outlive :func:`shutdown` and, when one of them releases a finished collective while the
    interpreter exits, the process aborts (``terminate called without an active exception``). Imported
    before, the argument binds the placeholder and :func:`shutdown` joins the group's threads.
    """
    import torch._dynamo  # noqa: F401  (imports torch.distributed.fsdp)


def shutdown() -> None:
    """Leave the process group (no-op without one): every collective has completed (they all wait), and
    destroying the group joins its communication threads, so none outlives the interpreter."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def communication_threads() -> list[str]:
    """Names of this process's live gloo/NCCL threads (Linux ``/proc``; empty elsewhere). After
    :func:`shutdown` there are none: a group still referenced somewhere would leave its threads running."""
    tasks = "/proc/self/task"
    if not os.path.isdir(tasks):
        return []
    names = []
    for tid in os.listdir(tasks):
        try:
            with open(f"{tasks}/{tid}/comm") as fh:
                names.append(fh.read().strip())
        except OSError:  # the thread ended while listing
            continue
    return sorted(n for n in names if "gloo" in n or "nccl" in n)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:400] or type(exc).__name__


def _collective(what: str, fn: Callable[[], T]) -> T:
    """Run a collective, turning any failure into a :class:`DistributedError` that says what happened."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - gloo/NCCL raise RuntimeError subclasses of several kinds
        raise DistributedError(
            f"rank {rank()} of {world_size()}: {what} failed — another rank died or did not answer within "
            f"the process-group timeout ({_timeout_s:g} s, --dist-timeout); the run stops here and resumes "
            f"from its last complete checkpoint (--resume). Cause: {_one_line(exc)}") from exc


def shard(n: int, of_rank: int | None = None, world: int | None = None) -> range:
    """This rank's contiguous share of ``n`` global slots: ``range(n·r//P, n·(r+1)//P)``.

    Shares differ by at most one slot; with ``n < P`` some ranks get none.
    """
    r = rank() if of_rank is None else of_rank
    p = world_size() if world is None else world
    return range(n * r // p, n * (r + 1) // p)


def optimizer_params(optimizer: torch.optim.Optimizer) -> list[torch.Tensor]:
    """Every parameter of ``optimizer``'s groups, in order."""
    return [p for group in optimizer.param_groups for p in group["params"]]


def all_reduce_grads(params: torch.optim.Optimizer | Iterable[torch.Tensor]) -> None:
    """Sum the ``.grad`` of ``params`` (or of an optimiser's parameters) over ranks, in place.

    One flat all-reduce per dtype of all gradients (``Σ numel`` values) plus one flag per parameter, so a
    gradient that is ``None`` on every rank stays ``None`` (Adam skips it, as in a single process) and one
    that is ``None`` on some ranks counts as zeros there. Each rank's loss must be weighted so that the sum
    over ranks is the whole step's loss (see :func:`shard`).
    """
    if not active():
        return
    ps = optimizer_params(params) if isinstance(params, torch.optim.Optimizer) else list(params)
    groups: dict[tuple[torch.dtype, torch.device], list[torch.Tensor]] = {}
    for p in ps:
        groups.setdefault((p.dtype, p.device), []).append(p)
    for (dtype, device), group in groups.items():
        flags = torch.tensor([p.grad is not None for p in group], dtype=dtype, device=device)
        flat = torch.cat([flags] + [(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1)
                                    for p in group])
        _collective("all-reduce of gradients", lambda f=flat: dist.all_reduce(f))
        seen = flat[:len(group)].tolist()  # ranks that had a gradient, per parameter
        offset = len(group)
        for count, p in zip(seen, group):
            if count > 0:
                p.grad = flat[offset:offset + p.numel()].view_as(p).clone()
            offset += p.numel()


def all_reduce_sum(x: torch.Tensor) -> torch.Tensor:
    """``x`` summed over ranks (a new tensor; ``x`` itself without a process group)."""
    if not active():
        return x
    y = x.clone()
    _collective("all-reduce", lambda: dist.all_reduce(y))
    return y


def all_reduce_scalars(values: Mapping[str, float | torch.Tensor]) -> dict[str, float | torch.Tensor]:
    """Named scalars (floats or 0-dim tensors) summed over ranks (every rank must pass the same names in the same
    order). Without a process group they are returned as given; with one, as 0-dim float64 tensors on the
    group's device, so that a step's scalars reach the host only when the engine logs them."""
    if not active():
        return dict(values)
    device = _comm_device()
    stacked = torch.stack([torch.as_tensor(v, dtype=torch.float64).to(device) for v in values.values()])
    return dict(zip(values, all_reduce_sum(stacked).unbind()))


def _comm_device() -> torch.device:
    """Where small tensors for the process group live (NCCL needs the rank's GPU)."""
    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else torch.device("cpu")


def broadcast_modules(modules: Iterable[nn.Module]) -> None:
    """Copy rank 0's parameters and buffers into every rank's ``modules`` (in place)."""
    if not active():
        return
    for module in modules:
        for tensor in list(module.parameters()) + list(module.buffers()):
            _collective("broadcast of the model", lambda t=tensor: dist.broadcast(t.data, src=0))


def broadcast_object(obj: Any) -> Any:
    """Rank 0's ``obj`` on every rank (picklable; ``obj`` itself without a process group)."""
    if not active():
        return obj
    box = [obj]
    _collective("broadcast", lambda: dist.broadcast_object_list(box, src=0))
    return box[0]

