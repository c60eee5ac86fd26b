"""Checks of COLMAP model files before pycolmap reads them, so that damage is reported by file name.

pycolmap's readers do not check for short reads. Measured with pycolmap 4.2: a truncated ``cameras.bin``
loads without an error (the cut-off parameters are garbage), a truncated ``points3D.bin`` allocates until
memory runs out, and a text file cut at a line boundary loads as a smaller model. So, before pycolmap reads
a model:

* :func:`check_binary` walks a ``.bin`` file's record framing only (record counts, name terminators and
  the lengths of the variable-length arrays; no value is interpreted, pycolmap reads them all) and reports
  a file that ends early or runs on past its last record;
* :func:`check_text` compares the record count in a ``.txt`` file's ``# Number of ...`` header, where
  COLMAP wrote one, with the records present.

Binary layouts (little-endian), per record after a ``uint64`` count:

* ``cameras``: u32 id, i32 model, u64 width, u64 height, f64 × (the model's parameter count);
* ``images``: u32 id, 7 f64 pose, u32 camera id, NUL-terminated name, u64 n, n × (2 f64 + u64);
* ``points3D``: u64 id, 3 f64, 3 u8 colour, f64 error, u64 n, n × (u32 + u32);
* ``rigs``: u32 id, u32 n sensors, [i32 + u32 reference sensor], (n - 1) × (i32 + u32 + u8 has-pose,
  [7 f64 pose]);
* ``frames``: u32 id, u32 rig id, 7 f64 pose, u32 n, n × (i32 + u32 + u64).
"""
from __future__ import annotations

import re
import struct
from pathlib import Path

import pycolmap

from nsplat.errors import DataError

_U8, _U32, _I32, _U64 = (struct.Struct(f) for f in ("<B", "<I", "<i", "<Q"))
_POSE = 7 * 8


class _Cursor:
    """Reads framing fields of one binary model file, raising a :class:`DataError` past its end."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def skip(self, n: int, what: str) -> None:
        if self.pos + n > len(self.data):
            raise DataError(f"{self.path}: truncated or corrupt: {what} needs {n} bytes at byte {self.pos}, "
                            f"the file has {len(self.data)}")
        self.pos += n

    def read(self, fmt: struct.Struct, what: str) -> int:
        start = self.pos
        self.skip(fmt.size, what)
        return int(fmt.unpack_from(self.data, start)[0])

    def name(self, what: str) -> None:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DataError(f"{self.path}: truncated or corrupt: {what} has no terminating NUL byte")
        self.pos = end + 1


def _num_params(path: Path, record: int, model_id: int) -> int:
    try:
        model = pycolmap.CameraModelId(model_id)
        return int(pycolmap.Camera.create_from_model_id(0, model, 1.0, 1, 1).params.size)
    except (ValueError, TypeError):
        raise DataError(f"{path}: camera record {record}: unknown camera model id {model_id} "
                        f"(truncated or corrupt?)") from None


def _cameras(c: _Cursor, i: int) -> None:
    c.skip(4, f"camera {i} id")
    model = c.read(_I32, f"camera {i} model")
    c.skip(16, f"camera {i} size")
    c.skip(8 * _num_params(c.path, i, model), f"camera {i} parameters")


def _images(c: _Cursor, i: int) -> None:
    c.skip(4 + _POSE + 4, f"image {i} id, pose and camera")
    c.name(f"image {i} name")
    n = c.read(_U64, f"image {i} point count")
    c.skip(24 * n, f"image {i} points ({n})")


def _points3d(c: _Cursor, i: int) -> None:
    c.skip(8 + 24 + 3 + 8, f"point {i}")
    n = c.read(_U64, f"point {i} track length")
    c.skip(8 * n, f"point {i} track ({n})")


def _rigs(c: _Cursor, i: int) -> None:
    c.skip(4, f"rig {i} id")
    n = c.read(_U32, f"rig {i} sensor count")
    if n > 0:
        c.skip(8, f"rig {i} reference sensor")
    for j in range(max(n - 1, 0)):
        c.skip(8, f"rig {i} sensor {j}")
        if c.read(_U8, f"rig {i} sensor {j} pose flag"):
            c.skip(_POSE, f"rig {i} sensor {j} pose")


def _frames(c: _Cursor, i: int) -> None:
    c.skip(4 + 4 + _POSE, f"frame {i}")
    n = c.read(_U32, f"frame {i} data count")
    c.skip(16 * n, f"frame {i} data ({n})")


_RECORDS = {"cameras": _cameras, "images": _images, "points3D": _points3d, "rigs": _rigs, "frames": _frames}


def check_binary(path: Path) -> None:
    """Raise a one-line :class:`DataError` naming ``path`` (``<kind>.bin``) when its records do not
    exactly fill the file."""
    c = _Cursor(path)
    count = c.read(_U64, "record count")
    record = _RECORDS[path.stem]
    for i in range(count):
        record(c, i)
    if c.pos != len(c.data):
        raise DataError(f"{path}: corrupt: {len(c.data) - c.pos} bytes after the last of {count} records")


_HEADER = re.compile(r"#\s*Number of \w+:\s*(\d+)")


def check_text(path: Path) -> None:
    """Raise a one-line :class:`DataError` naming ``path`` (``<kind>.txt``) when its ``# Number of``
    header promises more or fewer records than it holds (``images.txt`` has two lines per image)."""
    lines = path.read_text(errors="replace").splitlines()
    match = next((m for m in map(_HEADER.match, lines) if m), None)
    if match is None:
        return
    data = [ln for ln in lines if not ln.startswith("#")]
    if path.stem == "images":
        found = (len(data) + 1) // 2  # the last image's (possibly empty) points line may lack its newline
    else:
        found = sum(1 for ln in data if ln.strip())
    if found != int(match.group(1)):
        raise DataError(f"{path}: truncated or corrupt: the header says {match.group(1)} records, "
                        f"the file holds {found}")
