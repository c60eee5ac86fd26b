"""Command line: ``train`` (default), ``eval`` and ``render`` over the task registry.

Usage::

    python train.py                                   # the default config (configs/default.yaml)
    python train.py --config configs/lego.yaml optim.lr=0.005 --device cuda
    python train.py --config configs/lego.yaml --run runs/lego --resume
    python train.py eval --run runs/lego --split test
    python train.py render --run runs/lego
    python train.py view --run runs/lego                 # web viewer (nsplat/viewer), --help for options
    python train.py export --run runs/lego --format ply  # or npz
    python train.py --config configs/lego.yaml viewer=true   # live view while training
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import torch
import yaml

from nsplat.config import ConfigError, load_config, read_yaml, to_dict
from nsplat.runctx import RunContext
from nsplat.tasks import get_task
from nsplat.viewer import live

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_CONFIG = REPO_ROOT / "configs" / "default.yaml"
log = logging.getLogger("nsplat")


def _parse(argv: list[str]) -> argparse.Namespace:
    commands = {"train", "eval", "render"}
    command = "train"
    if argv and argv[0] in commands:
        command, argv = argv[0], argv[1:]
    p = argparse.ArgumentParser(prog="train.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None, help="YAML config (default: configs/default.yaml)")
    p.add_argument("--run", type=Path, default=None, help="run folder (default: runs/<config>-<time>)")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --run")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--seed", type=int, default=None, help="global seed (default: from the config, else 0)")
    p.add_argument("--split", default="test", help="split for `eval`")
    p.add_argument("overrides", nargs="*", help="config overrides key=value (dotted keys)")
    args = p.parse_args(argv)
    args.command = command
    return args


def _device(name: str | None) -> torch.device:
    if name is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device {name}: CUDA is not available on this machine")
    return dev


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("view", "export"):  # own options: nsplat/viewer/commands.py
        from nsplat.viewer.commands import main as viewer_main
        return viewer_main(argv[0], argv[1:])
    args = _parse(argv)
    try:
        if args.command == "train":
            return _train(args)
        return _post(args)
    except ConfigError as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2


def _train(args: argparse.Namespace) -> int:
    if args.resume:
        if args.run is None:
            raise SystemExit("--resume needs --run DIR")
        raw = read_yaml(args.run / "config.yaml")
    else:
        raw = read_yaml(args.config or DEFAULT_CONFIG)
    if "task" not in raw:
        raise ConfigError("config has no 'task' key")
    task = get_task(raw["task"])
    overrides, live_opts = live.split_overrides(args.overrides)
    cfg = load_config(task.Config, raw, overrides)
    seed = args.seed if args.seed is not None else int(getattr(cfg, "seed", 0))
    if args.run is None:
        stem = (args.config or DEFAULT_CONFIG).stem
        args.run = REPO_ROOT / "runs" / f"{stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    args.run.mkdir(parents=True, exist_ok=True)
    (args.run / "config.yaml").write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    ctx = RunContext(run_dir=args.run, device=_device(args.device), seed=seed, resume=args.resume)
    log.info("run folder: %s", args.run)
    with live.session(live_opts):
        task.run(cfg, ctx)
    return 0


def _post(args: argparse.Namespace) -> int:
    if args.run is None:
        raise SystemExit(f"`{args.command}` needs --run DIR")
    raw = read_yaml(args.run / "config.yaml")
    task = get_task(raw["task"])
    cfg = load_config(task.Config, raw, args.overrides)
    ctx = RunContext(run_dir=args.run, device=_device(args.device),
                     seed=int(getattr(cfg, "seed", 0)), resume=True)
    fn = getattr(task, "evaluate" if args.command == "eval" else "render", None)
    if fn is None:
        raise SystemExit(f"task {raw['task']!r} has no `{args.command}` command")
    if args.command == "eval":
        fn(cfg, ctx, split=args.split)
    else:
        fn(cfg, ctx)
    return 0
