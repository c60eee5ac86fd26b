"""The ``view`` and ``export`` sub-commands of ``train.py``.

Usage::

    python train.py view --run DIR [--host 127.0.0.1] [--port 8080] [--device cpu]
                         [--resolution 256] [--samples 16] [--eps 0.01]
    python train.py export --run DIR --format ply|npz [--out PATH] [--device cpu]

Bad input (missing run folder, no checkpoint, unknown format) is reported on one line, exit status 2.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import torch

from nsplat.export import FORMATS, export
from nsplat.viewer.model import RenderSettings
from nsplat.viewer.runs import RunError, load_run
from nsplat.viewer.server import serve

log = logging.getLogger("nsplat")


class UsageError(Exception):
    """Bad command-line input (reported on one line, exit 2)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line instead of usage + message
        raise UsageError(f"{self.prog}: {message}")


def _parser(command: str) -> argparse.ArgumentParser:
    p = _Parser(prog=f"train.py {command}", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, required=True, help="run folder (written by `python train.py`)")
    p.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    if command == "view":
        p.add_argument("--host", default="127.0.0.1", help="address to bind (default: 127.0.0.1, local only)")
        p.add_argument("--port", type=int, default=8080, help="port (default: 8080)")
        p.add_argument("--resolution", type=int, default=256, help="initial longest image side (px)")
        p.add_argument("--samples", type=int, default=16, help="initial samples per pixel")
        p.add_argument("--eps", type=float, default=0.01, help="initial sampler error bound ε")
    else:
        p.add_argument("--format", required=True, help=f"one of {', '.join(FORMATS)}")
        p.add_argument("--out", type=Path, default=None, help="output file (default: RUN/export/surfels.FORMAT)")
    return p


def main(command: str, argv: list[str]) -> int:
    """Run ``view`` or ``export`` with its arguments ``argv``; returns the exit status."""
    try:
        args = _parser(command).parse_args(argv)
        if command == "export" and args.format not in FORMATS:
            raise UsageError(f"--format: unknown format {args.format!r}; expected one of {', '.join(FORMATS)}")
        if args.device.startswith("cuda") and not torch.cuda.is_available():
            raise UsageError(f"--device {args.device}: CUDA is not available on this machine")
        model = load_run(args.run, args.device)
    except (UsageError, RunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if command == "export":
        path = export(model, args.format, args.out or args.run / "export" / f"surfels.{args.format}")
        log.info("wrote %s (%d surfels, %d features)", path, model.num_points, model.features.shape[1])
        return 0
    try:
        settings = RenderSettings(samples=args.samples, eps=args.eps, resolution=args.resolution)
    except ValueError as exc:
        print(f"error: train.py view: {exc}", file=sys.stderr)
        return 2
    serve(model, args.host, args.port, settings)
    return 0
