"""The one place that resolves the repository, data and config roots.

* :func:`repo_root` — the checkout (``<repo>``) when nsplat runs from one, else the current folder;
  relative paths in configs (caches, PLYs, scene folders) are taken relative to it.
* :func:`data_root` — the shared, read-only data folder: ``$NSPLAT_DATA`` when set, else
  ``<repo>/../shared/data``.
* :func:`config_dir` — the shipped configs (``configs/`` of the checkout, installed as package data
  ``nsplat/configs`` so the console script works outside the checkout).
"""
from __future__ import annotations

import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parents[1]


def _checkout() -> Path | None:
    """The repository root when this package is imported from a checkout (editable install)."""
    root = _PACKAGE.parent
    return root if (root / "pyproject.toml").is_file() and (root / "nsplat").is_dir() else None


def repo_root() -> Path:
    """The checkout holding this package, or the current folder for an installed package."""
    return _checkout() or Path.cwd()


def data_root() -> Path:
    """The shared data folder: ``$NSPLAT_DATA``, else ``<repo>/../shared/data``."""
    env = os.environ.get("NSPLAT_DATA")
    return Path(env).expanduser() if env else repo_root().parent / "shared" / "data"


def config_dir() -> Path:
    """Folder of the shipped YAML configs (the checkout's ``configs/`` or the installed package data)."""
    checkout = _checkout()
    if checkout is not None and (checkout / "configs").is_dir():
        return checkout / "configs"
    return _PACKAGE / "configs"


def resolve(path: str | Path, base: Path | None = None) -> Path:
    """``path`` with ``~`` expanded; relative paths are taken relative to ``base`` (default :func:`repo_root`)."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else (base or repo_root()) / p


def resolve_data(path: str | Path | None, default: str) -> Path:
    """A data path from a config: empty → ``data_root()/default``; relative → relative to the repo root."""
    return resolve(path) if path else data_root() / default
