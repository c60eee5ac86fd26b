"""``nsplat data fetch|prepare`` (also ``python train.py data ...`` and ``python -m nsplat.data ...``).

Usage::

    nsplat data fetch lego --resolution 400     # NeRF-synthetic lego, plus the 400² copy configs/lego.yaml uses
    nsplat data fetch nerf_synthetic --resolution 400   # all eight NeRF-synthetic scenes, from one download
    nsplat data fetch chair ship                # some of them (one download of nerf_synthetic.zip)
    nsplat data fetch dss                       # the four DSS point clouds (configs/reconstruct_*.yaml)
    nsplat data fetch tum_fr1_rpy               # a TUM RGB-D sequence, into rgbd/rgbd_dataset_freiburg1_rpy
    nsplat data prepare chair --resolution 200  # another downscale of a fetched NeRF-synthetic scene
    nsplat data fetch lego --archive ~/Downloads/nerf_synthetic.zip   # a copy downloaded by hand

Data goes to ``$NSPLAT_DATA`` (default ``$XDG_DATA_HOME/nsplat``, i.e. ``~/.local/share/nsplat``) or
``--root``. An interrupted download resumes when the same command runs again. Sources, checksums and what
is verified: docs/data.md. Errors print one line on stderr and exit with code 2.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from nsplat.data.fetch import DATASETS, GROUPS, LAYOUTS, Fetched, FetchError, Remote, expand, fetch_together
from nsplat.data.nerf_scenes import NERF_SCENES
from nsplat.data.paths import data_root
from nsplat.data.prepare import prepare

#: Environment variable that replaces the published base URLs (like ``--mirror``).
MIRROR_ENV = "NSPLAT_DATA_MIRROR"
#: The datasets published as one archive, to which --sha256 and --archive apply.
ARCHIVED = frozenset(name for name, ds in DATASETS.items() if ds.scene is not None)
#: What ``--resolution`` applies to: the NeRF-synthetic scenes.
SCALABLE = f"the NeRF-synthetic scenes ({', '.join(NERF_SCENES)}, or nerf_synthetic for all eight)"


class UsageError(Exception):
    """A command line that cannot be parsed."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser that raises :class:`UsageError` instead of printing usage and exiting."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message}")


def _parser(prog: str) -> argparse.ArgumentParser:
    p = _Parser(prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="action", required=True, metavar="{fetch,prepare}", parser_class=_Parser)
    f = sub.add_parser("fetch", help="download, verify and unpack datasets into the data root")
    f.add_argument("datasets", nargs="+", choices=sorted([*DATASETS, *GROUPS]), metavar="DATASET",
                   help=f"one or more of: {', '.join(sorted([*DATASETS, *GROUPS]))} (nerf_synthetic: its eight "
                        f"scenes)")
    f.add_argument("--resolution", type=int, default=None, metavar="N",
                   help="NeRF-synthetic scenes: also write the N-pixel copy nerf_synthetic/<scene>_N "
                        "(configs/nerf_synthetic.yaml reads <scene>_400)")
    f.add_argument("--mirror", default=os.environ.get(MIRROR_ENV) or None, metavar="URL",
                   help=f"fetch every file as URL/<file name> instead of from its published source "
                        f"(default: ${MIRROR_ENV})")
    f.add_argument("--sha256", default=None, metavar="HEX",
                   help="NeRF-synthetic scenes, tum_*: require this sha256 of the archive (nerf_synthetic.zip, "
                        "<sequence>.tgz)")
    f.add_argument("--archive", type=Path, default=None, metavar="FILE",
                   help="NeRF-synthetic scenes, tum_*: use this archive (downloaded by hand) instead of downloading")
    pr = sub.add_parser("prepare", help="write a downscaled copy of a fetched NeRF-synthetic scene")
    pr.add_argument("scene", choices=NERF_SCENES, metavar="SCENE",
                    help=f"the fetched NeRF-synthetic scene: one of {', '.join(NERF_SCENES)}")
    pr.add_argument("--resolution", type=int, required=True, metavar="N", help="output width in pixels")
    for q in (f, pr):
        q.add_argument("--root", type=Path, default=None, help="data folder (default: $NSPLAT_DATA, else "
                                                              "$XDG_DATA_HOME/nsplat or ~/.local/share/nsplat)")
        q.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def _check(args: argparse.Namespace) -> None:
    """Option combinations that argparse does not check."""
    if args.resolution is not None and args.resolution < 1:
        raise UsageError(f"--resolution: expected a positive number of pixels, got {args.resolution}")
    if args.action != "fetch":
        return
    names = expand(args.datasets)
    if args.resolution is not None and not set(NERF_SCENES).intersection(names):
        raise UsageError(f"--resolution applies to {SCALABLE} only")
    for flag in ("sha256", "archive"):
        if getattr(args, flag) is not None and len({DATASETS[n].files for n in names if n in ARCHIVED}) != 1:
            raise UsageError(f"--{flag} applies to one dataset published as an archive (a tum_* sequence, or "
                             f"NeRF-synthetic scenes, which share nerf_synthetic.zip); name datasets of one archive")
    if args.sha256 is not None and (len(args.sha256) != 64 or any(c not in "0123456789abcdefABCDEF"
                                                                  for c in args.sha256)):
        raise UsageError(f"--sha256: expected 64 hexadecimal digits, got {args.sha256!r}")


def _fetch(args: argparse.Namespace, root: Path) -> None:
    """Fetch the named datasets, those of one archive with one download, and prepare the scaled copies."""
    units: dict[tuple[Remote, ...], list[str]] = {}  # the datasets of the same files, in order of appearance
    for name in expand(args.datasets):
        if name in NERF_SCENES and args.resolution is not None:
            scaled = root / f"{DATASETS[name].dest}_{args.resolution}"
            if scaled.is_dir():  # the copy the configs read is there; the originals are not needed
                print(f"{name}_{args.resolution}: already in {scaled}")
                continue
        units.setdefault(DATASETS[name].files, []).append(name)
    for names in units.values():
        archived, noted = names[0] in ARCHIVED, set()

        def report(name: str, done: Fetched) -> None:
            print(f"{name}: {'already in' if done.already else 'fetched into'} {done.dest}")
            for rec in done.files:
                if rec["checksum"] != "verified" and rec["sha256"] not in noted:
                    noted.add(rec["sha256"])
                    print(f"  {rec['file']}: sha256 {rec['sha256']} ({rec['bytes']} bytes); no checksum is published "
                          f"for it, so only {LAYOUTS[DATASETS[name].layout].verified} were checked (--sha256 "
                          f"{rec['sha256']} requires this file next time)")

        fetched = fetch_together(names, root, mirror=args.mirror, sha256=args.sha256 if archived else None,
                                 archive=args.archive if archived else None, progress=not args.quiet, report=report)
        if args.resolution is not None:
            for name, done in zip(names, fetched):
                if name in NERF_SCENES:
                    _prepare(done.dest, args.resolution, not args.quiet)


def _prepare(src: Path, resolution: int, progress: bool) -> None:
    dest, already = prepare(src, resolution, progress=progress)
    print(f"{dest.name}: {'already in' if already else 'written to'} {dest}")


def main(argv: list[str], prog: str = "nsplat data") -> int:
    """Run ``data fetch`` or ``data prepare`` with ``argv``; returns the exit status (0, 2 user error,
    130 interrupted)."""
    try:
        args = _parser(prog).parse_args(argv)
        _check(args)
        root = (args.root or data_root()).expanduser().absolute()
        if args.action == "fetch":
            _fetch(args, root)
        else:
            _prepare(root / DATASETS[args.scene].dest, args.resolution, not args.quiet)
    except UsageError as exc:
        print(f"usage error: {exc} (see {prog} --help)", file=sys.stderr)
        return 2
    except FetchError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; run the same command again to resume the download", file=sys.stderr)
        return 130
    if root != data_root().expanduser().absolute():
        print(f"note: set NSPLAT_DATA={root} so that the configs and loaders find this data")
    return 0
