"""The one place that resolves the repository, data and config roots.

* :func:`repo_root` — the checkout (``<repo>``) when nsplat runs from one, else the current folder;
  relative paths in configs (caches, PLYs, scene folders) are taken relative to it.
* :func:`data_root` — the data folder: ``$NSPLAT_DATA`` when set, else the user data folder
  ``$XDG_DATA_HOME/nsplat`` (default ``~/.local/share/nsplat``); ``nsplat data fetch`` fills it (docs/data.md).
  A config path may start with ``$NSPLAT_DATA/`` to name a place inside it, whether the variable is set or not.
* :func:`config_dir` — the shipped configs (``configs/`` of the checkout, installed as package data
  ``nsplat/configs`` so the console script works outside the checkout).
"""
from __future__ import annotations

import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parents[1]
#: Leading component of a config path inside the data root (``$NSPLAT_DATA/nerf_synthetic/lego_400``).
DATA_PREFIX = "$NSPLAT_DATA"


def _checkout() -> Path | None:
    """The repository root when this package is imported from a checkout (editable install)."""
    root = _PACKAGE.parent
    return root if (root / "pyproject.toml").is_file() and (root / "nsplat").is_dir() else None


def repo_root() -> Path:
    """The checkout holding this package, or the current folder for an installed package."""
    return _checkout() or Path.cwd()


def data_root() -> Path:
    """The data folder: ``$NSPLAT_DATA``, else ``$XDG_DATA_HOME/nsplat``, else ``~/.local/share/nsplat``."""
    env = os.environ.get("NSPLAT_DATA")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_DATA_HOME")
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".local" / "share"
    return base / "nsplat"


def config_dir() -> Path:
    """Folder of the shipped YAML configs (the checkout's ``configs/`` or the installed package data)."""
    checkout = _checkout()
    if checkout is not None and (checkout / "configs").is_dir():
        return checkout / "configs"
    return _PACKAGE / "configs"


def resolve(path: str | Path, base: Path | None = None) -> Path:
    """``path`` with ``~`` expanded and a leading ``$NSPLAT_DATA`` replaced by :func:`data_root`; other
    relative paths are taken relative to ``base`` (default :func:`repo_root`)."""
    head, _, rest = str(path).partition("/")
    if head == DATA_PREFIX:
        return data_root() / rest
    p = Path(path).expanduser()
    return p if p.is_absolute() else (base or repo_root()) / p


def resolve_data(path: str | Path | None, default: str) -> Path:
    """A data path from a config: empty → ``data_root()/default``; otherwise as :func:`resolve`."""
    return resolve(path) if path else data_root() / default
