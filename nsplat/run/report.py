"""Result lines: what a command reports goes to stdout, progress and logs to stderr.

Tasks log their result lines (held-out metrics, shape distances, the files they wrote for the user) to
:data:`results`, a logger named ``nsplat.results``; the command line (:func:`nsplat.cli.main`) routes it to
stdout with :func:`to_stdout`, with the run folder first. Used as a library, ``nsplat.results`` is an ordinary
logger: its lines go wherever the application's logging sends them.
"""
from __future__ import annotations

import logging
import sys

#: The logger of result lines (``nsplat.results``).
results = logging.getLogger("nsplat.results")


def to_stdout(enabled: bool = True) -> None:
    """Send :data:`results` to stdout, message only and not to the root logger (``enabled=False``: silence it,
    e.g. on the ranks other than 0 under torchrun). Idempotent."""
    for handler in list(results.handlers):
        results.removeHandler(handler)
    handler = logging.StreamHandler(sys.stdout)
    handler.setFormatter(logging.Formatter("%(message)s"))
    results.addHandler(handler)
    results.propagate = False
    results.setLevel(logging.INFO if enabled else logging.WARNING)
