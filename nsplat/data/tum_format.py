"""The TUM RGB-D benchmark's text formats (Sturm et al., IROS 2012): frame lists (``timestamp filename``),
trajectories (``timestamp tx ty tz qx qy qz qw``, camera → world, Hamilton quaternion with the scalar last) and
the association of two streams of timestamps as the benchmark's ``associate.py`` does it. Malformed files raise a
one-line :class:`~nsplat.errors.DataError` naming the file and line.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from nsplat.errors import DataError


def text_rows(path: Path, columns: int, what: str) -> list[tuple[int, list[str]]]:
    """Whitespace-separated rows of ``path`` (``#`` comments and blank lines skipped), each ``columns`` wide, with
    their line numbers in the file: ``[(line, values)]``."""
    if not path.is_file():
        raise DataError(f"{path}: no such {what} file")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read the {what} file: {exc}") from None
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != columns:
            raise DataError(f"{path}:{n}: expected {columns} values on a {what} line, got {len(parts)}: {line!r}")
        rows.append((n, parts))
    if not rows:
        raise DataError(f"{path}: the {what} file lists nothing")
    return rows


def numbers(path: Path, row: list[str], n: int) -> list[float]:
    try:
        vals = [float(v) for v in row]
    except ValueError:
        raise DataError(f"{path}:{n}: expected numbers, got {' '.join(row)!r}") from None
    if not all(math.isfinite(v) for v in vals):
        raise DataError(f"{path}:{n}: a NaN or Inf value: {' '.join(row)!r}")
    return vals


def read_file_list(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """A TUM ``rgb.txt`` / ``depth.txt``: ``(timestamps [n] float64, file names relative to its folder)``."""
    path = Path(path)
    rows = text_rows(path, 2, "frame list")
    stamps = np.array([numbers(path, [r[0]], n)[0] for n, r in rows])
    return stamps, [r[1] for _, r in rows]


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``[n,4]`` ``(qx, qy, qz, qw)`` → rotation matrices ``[n,3,3]`` (normalised first)."""
    q = q / q.norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[n,3,3]`` → unit quaternions ``[n,4]`` ``(qx, qy, qz, qw)`` with ``qw >= 0``."""
    R = R.double()
    m = R.reshape(-1, 9)
    diag = torch.stack([1 + m[:, 0] - m[:, 4] - m[:, 8], 1 - m[:, 0] + m[:, 4] - m[:, 8],
                        1 - m[:, 0] - m[:, 4] + m[:, 8], 1 + m[:, 0] + m[:, 4] + m[:, 8]], -1)
    k = diag.argmax(-1)  # the largest component, computed without cancellation
    out = torch.empty(m.shape[0], 4, dtype=R.dtype)
    for i in range(m.shape[0]):
        r = R[i]
        s = 2.0 * math.sqrt(max(float(diag[i, k[i]]), 1e-300))
        if k[i] == 3:
            q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
        elif k[i] == 0:
            q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
        elif k[i] == 1:
            q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
        else:
            q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
        out[i] = torch.tensor([float(v) for v in q], dtype=R.dtype)
    out = out / out.norm(dim=-1, keepdim=True)
    return torch.where(out[:, 3:] < 0, -out, out)


def read_trajectory(path: str | Path) -> tuple[np.ndarray, torch.Tensor]:
    """A TUM trajectory file: ``(timestamps [n] float64, camera → world poses [n,4,4] float64)``."""
    path = Path(path)
    rows = text_rows(path, 8, "trajectory")
    vals = torch.tensor([numbers(path, r, n) for n, r in rows], dtype=torch.float64)
    qn = vals[:, 4:].norm(dim=-1)
    bad = (qn - 1.0).abs() > 1e-2
    if bool(bad.any()):
        n = int(torch.nonzero(bad)[0])
        raise DataError(f"{path}:{rows[n][0]}: pose {n + 1} has a quaternion of norm {float(qn[n]):.4f}, expected a "
                        f"unit quaternion (qx qy qz qw)")
    T = torch.eye(4, dtype=torch.float64).repeat(len(rows), 1, 1)
    T[:, :3, :3] = quat_to_matrix(vals[:, 4:])
    T[:, :3, 3] = vals[:, 1:4]
    return vals[:, 0].numpy(), T


def write_trajectory(path: str | Path, timestamps: Sequence[float] | np.ndarray, c2w: torch.Tensor,
                     comment: str = "") -> Path:
    """Write camera → world poses ``c2w [n,4,4]`` as a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``)."""
    path = Path(path)
    q = matrix_to_quat(c2w[:, :3, :3].detach().cpu())
    t = c2w[:, :3, 3].detach().cpu().double()
    lines = [f"# {comment}"] if comment else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for s, ti, qi in zip(np.asarray(timestamps, dtype=np.float64), t.tolist(), q.tolist()):
        lines.append(f"{s:.6f} " + " ".join(f"{v:.9f}" for v in ti + qi))
    path.write_text("\n".join(lines) + "\n")
    return path


def associate(first: np.ndarray, second: np.ndarray, max_dt: float, offset: float = 0.0) -> list[tuple[int, int]]:
    """Pair stamps of ``first`` with stamps of ``second + offset`` whose difference is below ``max_dt`` seconds.

    The candidate pairs are taken closest first and each stamp at most once (the TUM benchmark's
    ``associate.py``); returns ``(i, j)`` index pairs sorted by ``first``'s stamp.
    """
    a, b = np.asarray(first, np.float64), np.asarray(second, np.float64) + offset
    order = np.argsort(b)
    bs = b[order]
    cands = []
    for i, t in enumerate(a):
        lo, hi = np.searchsorted(bs, t - max_dt, "left"), np.searchsorted(bs, t + max_dt, "right")
        cands += [(abs(t - bs[k]), i, int(order[k])) for k in range(lo, hi) if abs(t - bs[k]) < max_dt]
    cands.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs, key=lambda p: a[p[0]])
