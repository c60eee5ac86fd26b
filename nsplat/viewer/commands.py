"""The ``view`` and ``export`` sub-commands of ``train.py``.

Usage::

    python train.py view --run DIR [--device cpu] [viewer.port=8080 viewer.host=0.0.0.0 viewer.render.samples=16 …]
    python train.py export --run DIR --format ply|3dgs|npz [--out PATH] [--device cpu]
    python train.py export --run DIR --format 3dgs [--antialiased] [--fit-epochs N]

``view`` takes the viewer's settings as ``viewer.<key>=value`` (:class:`nsplat.viewer.config.ViewerConfig`, the
same names as ``viewer=true`` on a training command). ``export`` prints the written file on stdout; ``3dgs``
writes the run's point-only model with nsplat's kernel converted to 3DGS's (:mod:`nsplat.gaussians.export`; a neural
run's
U-Net is not in the file): by default for classic 3DGS viewers, fitted to nsplat's renders of the training
cameras for ``--fit-epochs`` epochs (:mod:`nsplat.gaussians.fit`; 0: the conversion alone); with
``--antialiased`` for viewers with Mip-Splatting's compensation (the surfels' own opacities, no fit unless
``--fit-epochs`` asks). Bad input (missing run folder, no checkpoint, unknown format, a bad setting, an output
path that cannot be written) is reported on one line, exit status 2.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
from pathlib import Path

import torch

from nsplat.config import ConfigError
from nsplat.errors import DataError
from nsplat.gaussians.export import FILE_NAMES, FORMATS, export
from nsplat.gaussians.fit import FitSettings
from nsplat.run.context import RunFolderError
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
        p.add_argument("--antialiased", action="store_true",
                       help="3dgs: for viewers with Mip-Splatting's opacity compensation (gsplat's antialiased mode, "
                            "PlayCanvas's GSPLAT_AA); the header says SplatRenderMode: mip")
        p.add_argument("--fit-epochs", type=int, default=None, metavar="N",
                       help=f"3dgs: epochs of fitting the Gaussians to nsplat's renders of the training cameras "
                            f"(default: {FitSettings().epochs} for the classic file, 0 with --antialiased)")
    return p


def _fit_settings(args: argparse.Namespace) -> FitSettings | None:
    """The fit of an ``export`` command's arguments (``None`` for formats other than ``3dgs``)."""
    if args.format != "3dgs":
        if args.antialiased or args.fit_epochs is not None:
            raise UsageError(f"--format {args.format}: --antialiased and --fit-epochs are options of --format 3dgs")
        return None
    if args.fit_epochs is not None and args.fit_epochs < 0:
        raise UsageError(f"--fit-epochs: expected an int >= 0, got {args.fit_epochs}")
    epochs = args.fit_epochs if args.fit_epochs is not None else 0 if args.antialiased else FitSettings().epochs
    return FitSettings(epochs=epochs)


def _check_writable(out: Path, label: str, *, own_folder: bool = False) -> None:
    """Refuse an output path before any work when the file could not be written: a folder, a path in a folder that
    does not exist (``own_folder``: the export's own folder, created when its parent exists) or that this
    process cannot create files in (tried with a temporary file), or a file it may not overwrite."""
    if out.is_dir():
        raise UsageError(f"{label} {out}: is a folder; expected the path of the file to write")
    folder = out.parent
    if own_folder and not folder.exists():
        folder = folder.parent
    if folder.exists() and not folder.is_dir():
        raise UsageError(f"{label} {out}: cannot be written, {folder} is a file, not a folder")
    if not folder.is_dir():
        raise UsageError(f"{label} {out}: cannot be written, the folder {folder} does not exist")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise UsageError(f"{label} {out}: cannot be written, no file can be created in {folder} "
                         f"({exc.strerror or exc})") from None
    if out.exists() and not os.access(out, os.W_OK):
        raise UsageError(f"{label} {out}: cannot be written, no permission to overwrite the file")


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
        if command == "export":
            fit = _fit_settings(args)
            out = args.out if args.out is not None else args.run / "export" / FILE_NAMES[args.format]
            label = "--out" if args.out is not None else "export path"
            if args.run.is_dir() or args.out is not None:
                _check_writable(out, label, own_folder=args.out is None)
        model = load_run(args.run, args.device, points=command == "export" and args.format == "3dgs")
        if command == "export":
            try:
                path = export(model, args.format, out, antialiased=args.antialiased, fit=fit)
            except OSError as exc:
                raise UsageError(f"{label} {out}: cannot be written ({exc.strerror or exc})") from None
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
