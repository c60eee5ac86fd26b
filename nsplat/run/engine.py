"""The run engine: what every task does the same way (docs/architecture.md).

* :class:`LogConfig` — one cadence vocabulary, in steps: scalars, images, validation, checkpoints.
* :class:`Trainables` — what a task's ``build`` returns: modules, optimisers, schedulers, the batch
  generator and JSON-like ``extra`` state; its :meth:`~Trainables.payload` is the one checkpoint payload
  ``{step, modules, optimizers, schedulers, generator, extra}`` (RNG states are added by
  :func:`nsplat.run.checkpoint.save_checkpoint`).
* :class:`Engine` — the step loop with tqdm, TensorBoard, the live-view hook, timing, atomic checkpoints
  and exact resume. The task supplies its own ``step(step) -> scalars`` (GAN with two optimisers, refine's
  alternating groups and pruning, the fitter's per-view backward): the engine never looks inside.
  Under torchrun (:mod:`nsplat.run.distributed`) it starts every rank from rank 0's modules, and only rank 0
  shows progress, logs, validates, writes images and checkpoints; the step itself reduces its gradients.
* :func:`op_seed` — the op's seed for one named stream and step; :func:`write_json` — atomic JSON.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import torch
from torch import nn
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from nsplat.config import require_fields
from nsplat.run import distributed
from nsplat.run.checkpoint import NoCheckpoint, atomic_write, load_checkpoint, save_checkpoint

log = logging.getLogger(__name__)

#: Named op-seed streams: renders of the same step in different streams never share a seed.
STREAMS = ("train", "fit", "eval", "filter", "reposition", "batches", "densify")
_STREAM_BITS, _STEP_BITS = 8, 32


def op_seed(run_seed: int, stream: str, step: int = 0) -> int:
    """The op's sampling seed for ``step`` of ``stream`` in a run seeded ``run_seed``.

    ``seed·2⁴⁰ + stream·2³² + step`` (disjoint across runs, streams and steps for ``run_seed < 2²³`` and
    ``step < 2³²``, and below the op's limit ``2⁶³``).
    """
    if stream not in STREAMS:
        raise ValueError(f"stream: expected one of {STREAMS}, got {stream!r}")
    if not 0 <= run_seed < 2 ** (63 - _STREAM_BITS - _STEP_BITS) or not 0 <= step < 2 ** _STEP_BITS:
        raise ValueError(f"op_seed: run seed {run_seed} or step {step} out of range")
    return (run_seed << (_STREAM_BITS + _STEP_BITS)) + (STREAMS.index(stream) << _STEP_BITS) + step


def generator(run_seed: int, stream: str, step: int = 0) -> torch.Generator:
    """A CPU generator seeded by :func:`op_seed` (a function of the step: nothing to checkpoint)."""
    return torch.Generator().manual_seed(op_seed(run_seed, stream, step))


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically (temporary, fsync, rename)."""
    text = json.dumps(obj, indent=1).encode()
    atomic_write(Path(path), lambda fh: fh.write(text))


@dataclasses.dataclass
class LogConfig:
    """What the engine does every so many steps (0 disables; the last step always logs and checkpoints).

    Attributes:
        every: scalars to TensorBoard. images: image summaries. validate: the task's validation.
        checkpoint: atomic checkpoints. progress: show the tqdm bar.
    """

    every: int = 10
    images: int = 100
    validate: int = 100
    checkpoint: int = 100
    progress: bool = True

    def __post_init__(self) -> None:
        require_fields(self, every=">=1", images=">=0", validate=">=0", checkpoint=">=0")

    def due(self, cadence: int, step: int, last: bool) -> bool:
        """Whether a cadence of ``cadence`` steps fires after ``step`` (``last``: the final step)."""
        return cadence > 0 and (step % cadence == 0 or last)


@dataclasses.dataclass
class Trainables:
    """Everything a task optimises and checkpoints.

    Attributes:
        modules: named modules (their ``state_dict`` is saved; also what the allocation table inspects).
        optimizers, schedulers: named optimisers and LR schedulers.
        generator: the task's CPU generator (batch order, repositioning draws), or ``None``.
        extra: JSON-like task state saved with the checkpoint (history, counters, wall-clock seconds).
    """

    modules: dict[str, nn.Module]
    optimizers: dict[str, torch.optim.Optimizer] = dataclasses.field(default_factory=dict)
    schedulers: dict[str, Any] = dataclasses.field(default_factory=dict)
    generator: torch.Generator | None = None
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    def payload(self) -> dict[str, Any]:
        """The checkpoint payload (without ``step`` and RNG states, which :func:`save_checkpoint` adds)."""
        return {"modules": {k: m.state_dict() for k, m in self.modules.items()},
                "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
                "generator": None if self.generator is None else self.generator.get_state(),
                "extra": self.extra}

    def load(self, payload: Mapping[str, Any]) -> int:
        """Restore :meth:`payload` (RNG states are restored by :func:`load_checkpoint`); returns its step."""
        for key, group in (("modules", self.modules), ("optimizers", self.optimizers),
                           ("schedulers", self.schedulers)):
            saved = payload[key]
            if set(saved) != set(group):
                raise ValueError(f"checkpoint {key} {sorted(saved)} do not match this config's {sorted(group)}")
            for name, obj in group.items():
                obj.load_state_dict(saved[name])
        if self.generator is not None:
            self.generator.set_state(payload["generator"])
        self.extra = dict(payload["extra"])
        return int(payload["step"])


def checkpoint_rows(payload: Mapping[str, Any] | None, module: str, key: str) -> int | None:
    """Rows of tensor ``key`` of module ``module`` in a checkpoint (a scene's point count), or ``None``."""
    return None if payload is None else int(payload["modules"][module][key].shape[0])


def latest_payload(run_dir: Path, resume: bool, device: torch.device | str = "cpu") -> dict[str, Any] | None:
    """The latest checkpoint of ``run_dir`` when ``resume`` (``None`` when fresh or none exists yet)."""
    if not resume:
        return None
    try:
        return load_checkpoint(run_dir, map_location=device)
    except NoCheckpoint:
        log.info("no checkpoint in %s; starting from scratch", run_dir)
        return None


Hook = Callable[[int, SummaryWriter], dict[str, float]]
#: A step's scalars: floats or 0-dim tensors on any device (copied to the host when logged).
Scalars = Mapping[str, "float | torch.Tensor"]


def host_scalars(scalars: Scalars) -> dict[str, float]:
    """``scalars`` as Python floats (one device-to-host copy per tensor on an accelerator)."""
    return {name: float(value) for name, value in scalars.items()}


#: The hooks ``hook(done, view)`` run after every step of a loop that has a ``view`` (:func:`step_hook`).
_STEP_HOOKS: list[Callable[[int, Callable[[], Any]], None]] = []


@contextlib.contextmanager
def step_hook(hook: Callable[[int, Callable[[], Any]], None]) -> Iterator[None]:
    """Run ``hook(done, view)`` after every step for the duration of the block (the command line installs the
    live viewer's :func:`nsplat.viewer.live.step` this way, so the engine never imports the viewer)."""
    _STEP_HOOKS.append(hook)
    try:
        yield
    finally:
        _STEP_HOOKS.remove(hook)


@dataclasses.dataclass
class Engine:
    """The step loop (see the module docstring).

    Attributes:
        run_dir: checkpoints go to ``run_dir/checkpoints``, TensorBoard logs to ``run_dir/tb``.
        log: the cadences. steps: total steps of the schedule. desc: the progress bar's label.
    """

    run_dir: Path
    log: LogConfig
    steps: int
    desc: str = "train"

    def train(self, trainables: Trainables, step: Callable[[int], Scalars], *, start: int = 0,
              validate: Hook | None = None, images: Hook | None = None,
              view: Callable[[], Any] | None = None) -> dict[str, float]:
        """Run ``step(k)`` for ``k = start … steps-1``; returns the last step's scalars (floats).

        Args:
            trainables: what is checkpointed: its ``extra["seconds"]`` and ``extra["cpu_seconds"]`` accumulate the
                steps' wall and CPU time over every segment of a resumed run (``extra["cpu_since"]``: the step
                from which CPU time is counted, later than 0 when the run began before it was).
            step: the task's step; returns scalars, floats or 0-dim tensors (on any device). They are copied to
                the host only when logged (every ``log.every`` steps and the last), so a GPU step need not wait
                for its own results; ``time/step_s`` is then the host's time per step.
            start: the first step (a resumed run's checkpoint step).
            validate: ``f(done, writer) -> scalars`` every ``log.validate`` steps (logged too; the first two shown on
                the progress bar).
            images: ``f(done, writer)`` every ``log.images`` steps (image summaries).
            view: builds the live viewer's model, handed to the hooks installed by :func:`step_hook` (the command
                line's ``viewer=true``: :func:`nsplat.viewer.live.step`).

        Under torchrun the hooks, the writer, the bar and the checkpoints are rank 0's only (the other
        ranks meet it again in the next step's all-reduce, within the process-group timeout).
        """
        lg = self.log
        main = distributed.is_main()
        distributed.broadcast_modules(trainables.modules.values())
        writer = SummaryWriter(str(Path(self.run_dir) / "tb"), purge_step=start or None) if main else None
        bar = tqdm(total=self.steps, initial=start, desc=self.desc, dynamic_ncols=True,
                   disable=not (lg.progress and main))
        scalars: dict[str, float | torch.Tensor] = {}
        shown: dict[str, str] = {}  # the bar's postfix: the last logged step's scalars and last validation
        extra = trainables.extra
        if "cpu_seconds" not in extra:
            extra.update(cpu_seconds=0.0, cpu_since=start)
        try:
            for k in range(start, self.steps):
                t0, c0 = time.perf_counter(), time.process_time()
                scalars = step(k)
                dt = time.perf_counter() - t0
                extra["seconds"] = float(extra.get("seconds", 0.0)) + dt
                extra["cpu_seconds"] = float(extra["cpu_seconds"]) + time.process_time() - c0
                done, last = k + 1, k + 1 == self.steps
                bar.update(1)
                logged = lg.due(lg.every, done, last)
                if logged:  # between logs the step's tensors stay where they are: no device-to-host copy
                    scalars = host_scalars(scalars)
                    shown.update({n: f"{v:.4g}" for n, v in list(scalars.items())[:3]})
                    bar.set_postfix(shown)
                if not main:
                    continue
                if view is not None:
                    for hook in _STEP_HOOKS:
                        hook(done, view)
                if logged:
                    for name, value in scalars.items():
                        writer.add_scalar(name, value, done)
                    writer.add_scalar("time/step_s", dt, done)
                if validate is not None and lg.due(lg.validate, done, last):
                    checked = validate(done, writer)
                    for name, value in checked.items():
                        writer.add_scalar(name, value, done)
                    shown.update({n: f"{v:.4g}" for n, v in list(checked.items())[:2]})
                    bar.set_postfix(shown)
                if images is not None and lg.due(lg.images, done, last):
                    images(done, writer)
                if last or lg.due(lg.checkpoint, done, last):
                    save_checkpoint(self.run_dir, done, trainables.payload())
        finally:
            bar.close()
            if writer is not None:
                writer.close()
        return host_scalars(scalars)

    def resume(self, trainables: Trainables, payload: Mapping[str, Any] | None) -> int:
        """Restore ``payload`` into ``trainables`` (``None``: fresh start); returns the first step to run."""
        if payload is None:
            return 0
        start = trainables.load(payload)
        log.info("resumed at step %d", start)
        return start
