"""Exception classes for bad user input that the command line reports in one line (exit code 2)."""
from __future__ import annotations


class DataError(ValueError):
    """A data file (transforms JSON, image, PLY) is malformed; the message names the file (and the frame
    and field where there is one)."""
