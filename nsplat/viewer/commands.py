"""The ``view`` and ``export`` sub-commands of ``train.py``.

Usage::

    python train.py view --run DIR [--device cpu] [viewer.port=8080 viewer.host=0.0.0.0 viewer.render.samples=16 …]
    python train.py export --run DIR --format ply|3dgs|npz [--out PATH] [--device cpu]

``view`` takes the viewer's settings as ``viewer.<key>=value`` (:class:`nsplat.viewer.config.ViewerConfig`, the
same names as ``viewer=true`` on a training command). ``export`` prints the written file on stdout; ``3dgs``
writes the run's point-only model with nsplat's kernel converted to 3DGS's (:mod:`nsplat.export`; a neural run's
U-Net is not in the file). Bad input
(missing run folder, no checkpoint, unknown format, a bad setting) is reported on one line, exit status 2.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import torch

from nsplat.config import ConfigError
from nsplat.errors import DataError
from nsplat.export import FILE_NAMES, FORMATS, export
from nsplat.runctx import RunFolderError
from nsplat.viewer.config import split_viewer_overrides
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
        p.add_argument("settings", nargs="*", metavar="viewer.KEY=VALUE",
                       help="viewer settings (viewer.host, viewer.port, viewer.resolution, viewer.render.<render key>)")
    else:
        p.add_argument("--format", required=True, help=f"one of {', '.join(FORMATS)}")
        p.add_argument("--out", type=Path, default=None,
                       help="output file (default: RUN/export/surfels.ply, point_cloud.ply for 3dgs, surfels.npz)")
    return p


def _check_writable(out: Path) -> None:
    """Refuse ``--out`` before any work when the file could not be written: a folder, a path below a file,
    or a folder this user may not write to."""
    if out.is_dir():
        raise UsageError(f"--out {out}: is a folder; expected the path of the file to write")
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UsageError(f"--out {out}: cannot be written, {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"--out {out}: cannot be written, no permission to write in {parent}")


def main(command: str, argv: list[str]) -> int:
    """Run ``view`` or ``export`` with its arguments ``argv``; returns the exit status."""
    try:
        args = _parser(command).parse_args(argv)
        if command == "export" and args.format not in FORMATS:
            raise UsageError(f"--format: unknown format {args.format!r}; expected one of {', '.join(FORMATS)}")
        if args.device.startswith("cuda") and not torch.cuda.is_available():
            raise UsageError(f"--device {args.device}: CUDA is not available on this machine")
        cfg = None
        if command == "view":
            rest, cfg = split_viewer_overrides(args.settings)
            if rest:
                raise UsageError(f"unexpected argument {rest[0]!r}: the viewer's settings are viewer.<key>=value")
        if command == "export" and args.out is not None:
            _check_writable(args.out)
        model = load_run(args.run, args.device, points=command == "export" and args.format == "3dgs")
        if command == "export":
            path = export(model, args.format, args.out or args.run / "export" / FILE_NAMES[args.format])
            log.info("%d surfels, %d features", model.num_points, model.features.shape[1])
            if args.format == "3dgs" and model.task == "neural":
                log.info("3dgs: stage 1's surfels and colour; a neural run's U-Net is not in the file")
            print(path)
            return 0
    except (UsageError, RunError, RunFolderError, ConfigError, DataError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    serve(model, cfg)
    return 0
