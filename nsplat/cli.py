"""Command line: ``train`` (default), ``eval`` and ``render`` over the task registry.

Usage::

    python train.py                                   # the default config (configs/default.yaml)
    python train.py --config configs/lego.yaml geometry.optim.epochs=60 --device cuda
    python train.py --config configs/lego.yaml --run runs/lego --resume
    python train.py eval --run runs/lego --split test
    python train.py render --run runs/lego               # orbit.mp4
    python train.py render --run runs/lego --path test --outputs rgb,depth,normal,alpha --fps 10
    python train.py render --run runs/lego --path train-smooth --frames 240 --resolution 400
    python train.py render --run runs/lego --path camera_path.json   # nerfstudio's camera path file
    python train.py view --run runs/lego                 # web viewer (viewer.port=…, viewer.render.samples=…)
    python train.py export --run runs/lego --format ply  # or npz
    python train.py data fetch lego --resolution 400     # datasets into $NSPLAT_DATA (nsplat/data/commands.py)
    python train.py --config configs/lego.yaml viewer=true   # live view while training
    torchrun --nproc_per_node=2 train.py --config configs/lego.yaml   # data-parallel (docs/distributed.md)

Results (the run folder, then the metrics lines) go to stdout, progress and logs to stderr. User errors
(bad config, bad data files, a run folder that cannot be used as asked) print one line on stderr and exit
with code 2; a fresh start that fails leaves no run folder behind (docs/runs.md). Under
torchrun, a rank that loses the others (one died, or the ``--dist-timeout`` passed) prints one line and
exits with code 1.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import torch
import yaml

from nsplat.config import ConfigError, load_config, read_yaml, to_dict
from nsplat.data import commands as data_commands
from nsplat.data.paths import config_dir, repo_root
from nsplat.errors import DataError
from nsplat.ops.validation import AllocationError
from nsplat.render.video import RenderRequest
from nsplat.run import distributed, engine, report
from nsplat.run.checkpoint import CheckpointError, atomic_write
from nsplat.run.context import (
    RunContext,
    RunFolderError,
    RunLock,
    check_run_folder,
    clear_run_folder,
    config_differences,
    finished_at,
    lock_holder,
    mark_finished,
)
from nsplat.tasks import TASKS, get_task
from nsplat.viewer import commands as viewer_commands
from nsplat.viewer import live
from nsplat.viewer.config import split_viewer_overrides

DEFAULT_CONFIG = config_dir() / "default.yaml"


COMMANDS = ("train", "eval", "render")
#: Options of the ``render`` command (:class:`nsplat.render.video.RenderRequest`).
RENDER_OPTIONS = ("path", "outputs", "fps", "frames", "resolution")
#: Errors caused by the user's input: reported in one line, exit code 2, no traceback.
USER_ERRORS = (ConfigError, RunFolderError, DataError, CheckpointError, AllocationError, FileNotFoundError)


class UsageError(Exception):
    """A command line that cannot be parsed (unknown command or option)."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser that raises :class:`UsageError` instead of printing usage and exiting."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(message)


def _command(argv: list[str]) -> tuple[str, list[str]]:
    """Split off the sub-command; a bare word that is not ``key=value`` and not a command is an error."""
    if argv and argv[0] in COMMANDS:
        return argv[0], argv[1:]
    if argv and not argv[0].startswith("-") and "=" not in argv[0]:
        valid = ", ".join(COMMANDS + ("view", "export", "data"))
        raise UsageError(f"unknown command {argv[0]!r}; valid commands: {valid} (overrides are key=value)")
    return "train", argv


def _parse(argv: list[str]) -> argparse.Namespace:
    command, argv = _command(argv)
    p = _Parser(prog=_prog(), description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None,
                   help="YAML config: a path, or the name of a shipped config (default: default.yaml)")
    p.add_argument("--run", "--run-dir", dest="run", type=Path, default=None,
                   help="run folder (default: runs/<config>-<time>); under torchrun spell it --run-dir "
                        "(torchrun's own parser takes --run for its --run-path)")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --run")
    p.add_argument("--overwrite", action="store_true",
                   help="delete the contents of a non-empty --run folder and start afresh")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--seed", type=int, default=None, help="the config's seed (the override seed=N under its own name)")
    p.add_argument("--split", default="test", help="split for `eval`")
    p.add_argument("--path", default=None,
                   help="`render`: camera path: orbit (default), test, train-smooth or a nerfstudio camera_path.json")
    p.add_argument("--outputs", default=None, help="`render`: comma-separated rgb,depth,normal,alpha (default rgb)")
    p.add_argument("--fps", type=float, default=None, help="`render`: frame rate (default: the file's or eval.fps)")
    p.add_argument("--frames", type=int, default=None, help="`render`: frames of orbit and train-smooth "
                                                             "(default eval.orbit_frames)")
    p.add_argument("--resolution", type=int, default=None,
                   help="`render`: longest image side in pixels (default: the training images' size)")
    p.add_argument("--dist-timeout", type=float, default=distributed.DEFAULT_TIMEOUT_S, metavar="SECONDS",
                   help="under torchrun: seconds a process waits for the others in a collective before the "
                        "run stops with an error (must exceed rank 0's validation and checkpoint time; "
                        f"default {distributed.DEFAULT_TIMEOUT_S:g})")
    p.add_argument("overrides", nargs="*", help="config overrides key=value (dotted keys)")
    args = p.parse_intermixed_args(argv)  # options may come after overrides
    args.command = command
    if args.seed is not None:
        args.overrides.append(f"seed={args.seed}")
    bad = [o for o in args.overrides if "=" not in o]
    if bad:
        raise UsageError(f"unexpected argument {bad[0]!r}: overrides are key=value")
    if args.resume and args.overwrite:
        raise UsageError("--resume and --overwrite exclude each other")
    given = [f"--{k}" for k in RENDER_OPTIONS if getattr(args, k) is not None]
    if given and command != "render":
        raise UsageError(f"{given[0]} is an option of `render`")
    if not args.dist_timeout > 0:
        raise UsageError(f"--dist-timeout: expected > 0 seconds, got {args.dist_timeout}")
    return args


def _prog() -> str:
    """The name the program was started under (``train.py`` or the ``nsplat`` console script)."""
    return Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "nsplat"


def _device(name: str | None) -> torch.device:
    if name is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ConfigError(f"--device {name!r}: not a torch device ({_one_line(exc)})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: CUDA is not available on this machine")
    return dev


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(str(exc).split()) or type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code (0 success, 2 user error, 130 training interrupted)."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # progress and logs: stderr
    report.to_stdout()  # results (the run folder, metrics lines): stdout
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("view", "export"):  # own options: nsplat/viewer/commands.py
        return viewer_commands.main(argv[0], argv[1:])
    if argv and argv[0] == "data":  # own options: nsplat/data/commands.py
        return data_commands.main(argv[1:], prog=f"{_prog()} data")
    try:
        args = _parse(argv)
        if args.command == "train":
            return _train(args)
        return _post(args)
    except UsageError as exc:
        print(f"usage error: {_one_line(exc)} (see {_prog()} --help)", file=sys.stderr)
        return 2
    except ConfigError as exc:
        print(f"config error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except USER_ERRORS as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except distributed.DistributedError as exc:
        print(f"distributed error: {_one_line(exc)}", file=sys.stderr)
        return 1


def _config_path(path: Path | None) -> Path:
    """``--config``: a file path, else a shipped config of that name (``lego.yaml``); default ``default.yaml``."""
    if path is None:
        return DEFAULT_CONFIG
    shipped = config_dir() / path.name
    return shipped if not path.exists() and path.parent == Path(".") and shipped.is_file() else path


def _configs(args: argparse.Namespace) -> tuple[Any, Any, dict[str, Any] | None]:
    """(task module, config, the run's saved config dict when resuming); reads only."""
    saved = None
    if args.resume:
        if args.run is None:
            raise RunFolderError("--resume needs --run DIR")
        check_run_folder(args.run, resume=True, overwrite=False)
        raw = read_yaml(args.run / "config.yaml")
    else:
        raw = read_yaml(_config_path(args.config))
    if "task" not in raw:
        raise ConfigError("config has no 'task' key")
    task = get_task(raw["task"])
    overrides, args.viewer = split_viewer_overrides(args.overrides)
    cfg = load_config(task.Config, raw, overrides)
    if args.resume:
        saved = to_dict(load_config(task.Config, raw))
        changed = config_differences(saved, to_dict(cfg))
        if changed:
            raise RunFolderError(f"--resume: the overrides change {', '.join(changed)} of the run in {args.run}; "
                                 f"a resumed run keeps its config (start a new run to change them)")
    return task, cfg, saved


def _train(args: argparse.Namespace) -> int:
    task, cfg, _ = _configs(args)
    finished = finished_at(args.run) if args.resume else None
    if finished is not None:  # every rank reads the same folder: all leave here, before any collective
        report.results.info("run folder: %s", args.run)
        report.results.info("the run finished on %s: nothing to resume (its outputs are unchanged; `eval` or "
                            "`render` it, or start a new run)", finished)
        return 0
    seed = int(getattr(cfg, "seed", 0))
    device = distributed.local_device(_device(args.device))
    if not distributed.launched():
        return _train_run(args, task, cfg, seed, device)
    if not getattr(task, "DISTRIBUTED", False):
        parallel = [name for name in TASKS if getattr(get_task(name), "DISTRIBUTED", False)]
        raise ConfigError(f"task {cfg.task!r} does not run data-parallel; start it with python train.py "
                          f"(without torchrun); data-parallel tasks: {', '.join(sorted(parallel))}")
    distributed.init_from_env(device, args.dist_timeout)
    if not distributed.is_main():
        logging.getLogger().setLevel(logging.WARNING)  # rank 0 reports
        report.to_stdout(enabled=False)
    try:
        return _train_run(args, task, cfg, seed, device)
    finally:
        distributed.shutdown()


def _train_run(args: argparse.Namespace, task: Any, cfg: Any, seed: int, device: torch.device) -> int:
    """Prepare the run folder and run the task. Under torchrun rank 0 alone touches the folder; the other
    ranks receive its path (or its one-line error) from rank 0."""
    main, fresh = distributed.is_main(), not args.resume
    created, lock = False, None
    try:
        if main:
            created, lock = _lock_run_folder(args)
    except USER_ERRORS as exc:
        distributed.broadcast_object(("error", f"rank 0: {_one_line(exc)}"))
        raise
    try:
        if main and fresh:
            clear_run_folder(args.run)
            text = yaml.safe_dump(to_dict(cfg), sort_keys=False).encode()
            atomic_write(args.run / "config.yaml", lambda fh: fh.write(text))
        kind, value = distributed.broadcast_object(("ok", args.run))
        if kind == "error":
            raise RunFolderError(value)
        args.run = value
        ctx = RunContext(run_dir=args.run, device=device, seed=seed, resume=args.resume)
        report.results.info("run folder: %s", args.run)
        with live.session(args.viewer) if main else contextlib.nullcontext(), engine.step_hook(live.step):
            task.run(cfg, ctx)
        if main:
            mark_finished(args.run)
    except (KeyboardInterrupt, *USER_ERRORS) as exc:
        if main:
            resumable = any(args.run.rglob("latest"))  # a checkpoint was written
            failed_start = fresh and not resumable
            if failed_start:  # a failed or interrupted start leaves no half-made run behind
                clear_run_folder(args.run)
            lock.release()
            if failed_start and created:
                shutil.rmtree(args.run, ignore_errors=True)
            if isinstance(exc, KeyboardInterrupt):
                print(f"interrupted: continue from the last checkpoint with `{_prog()} --run {args.run} --resume`"
                      if resumable else "interrupted before the first checkpoint: nothing to resume", file=sys.stderr)
                return 130
        raise
    finally:
        if lock is not None:
            lock.release()
    return 0


def _lock_run_folder(args: argparse.Namespace) -> tuple[bool, RunLock]:
    """Check, create and lock ``args.run`` (default: ``runs/<config>-<time>``); returns (whether the folder
    was created, the held lock)."""
    if args.run is None:
        stem = (args.config or DEFAULT_CONFIG).stem
        args.run = repo_root() / "runs" / f"{stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    holder = lock_holder(args.run)
    if holder is not None:
        raise RunFolderError(f"run folder {args.run} is in use by process {holder}; wait for it to finish "
                             f"or use another --run")
    check_run_folder(args.run, resume=args.resume, overwrite=args.overwrite)
    created = not args.run.exists()
    args.run.mkdir(parents=True, exist_ok=True)
    lock = RunLock(args.run).acquire()  # the holder's folder: never removed here when this fails
    try:
        check_run_folder(args.run, resume=args.resume, overwrite=args.overwrite)  # again, under the lock
    except RunFolderError:
        lock.release()
        raise
    return created, lock


def _post(args: argparse.Namespace) -> int:
    if args.run is None:
        raise RunFolderError(f"`{args.command}` needs --run DIR")
    if not (args.run / "config.yaml").is_file():
        raise RunFolderError(f"`{args.command}`: {args.run} holds no run (no config.yaml)")
    raw = read_yaml(args.run / "config.yaml")
    if "task" not in raw:
        raise ConfigError(f"{args.run / 'config.yaml'} has no 'task' key")
    task = get_task(raw["task"])
    cfg = load_config(task.Config, raw, args.overrides)
    ctx = RunContext(run_dir=args.run, device=_device(args.device),
                     seed=int(getattr(cfg, "seed", 0)), resume=True)
    fn = getattr(task, "evaluate" if args.command == "eval" else "render", None)
    if fn is None:
        raise ConfigError(f"task {raw['task']!r} has no `{args.command}` command")
    if args.command == "eval":
        fn(cfg, ctx, split=args.split)
    elif getattr(task, "RENDER_PATHS", False):
        fn(cfg, ctx, _render_request(args))
    elif any(getattr(args, k) is not None for k in RENDER_OPTIONS):
        raise UsageError(f"task {raw['task']!r}: `render` writes the task's own images; "
                         f"{', '.join('--' + k for k in RENDER_OPTIONS)} apply to the neural task")
    else:
        fn(cfg, ctx)
    return 0


def _render_request(args: argparse.Namespace) -> RenderRequest:
    """The ``render`` command's :class:`RenderRequest` from its options (unset ones: the defaults)."""
    given = {k: getattr(args, k) for k in RENDER_OPTIONS if getattr(args, k) is not None}
    if "outputs" in given:
        given["outputs"] = tuple(o.strip() for o in given["outputs"].split(",") if o.strip())
    try:
        return RenderRequest(**given)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
