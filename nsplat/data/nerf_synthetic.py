"""Loader for NeRF-synthetic scenes (``transforms_{train,val,test}.json`` + RGBA PNGs).

Cameras arrive as OpenGL/Blender camera→world matrices and a horizontal field of view
(``camera_angle_x``); they are converted once, here, to the library's OpenCV world→camera
``viewmats`` and pixel intrinsics ``Ks`` (square pixels, principal point at the image centre).
Images are composited over a background colour (white by default, as in NeRF's evaluation) and
optionally resized, with the intrinsics scaled to match.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F

from nsplat.cameras import intrinsics_from_fov, opengl_c2w_to_viewmat, scale_intrinsics
from nsplat.data.views import PosedViews
from nsplat.errors import DataError

SPLITS = ("train", "val", "test")


def _image_path(root: Path, file_path: str) -> Path:
    p = root / file_path
    return p if p.suffix else p.with_suffix(".png")


def _resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Resize ``[B,H,W,C]`` to ``size = (H', W')``: area averaging when shrinking by an integer
    factor, antialiased bilinear otherwise."""
    B, H, W, C = x.shape
    if (H, W) == size:
        return x
    xc = x.permute(0, 3, 1, 2)
    if H % size[0] == 0 and W % size[1] == 0:
        out = F.interpolate(xc, size=size, mode="area")
    else:
        out = F.interpolate(xc, size=size, mode="bilinear", antialias=True, align_corners=False)
    return out.permute(0, 2, 3, 1).contiguous()


def _camera_angle(meta_path: Path, value: object) -> float:
    """``camera_angle_x`` as a float in (0, π) radians, or a :class:`DataError` naming file and field."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DataError(f"{meta_path}: field 'camera_angle_x': expected a number (radians), got {value!r}")
    if not 0 < float(value) < np.pi:
        raise DataError(f"{meta_path}: field 'camera_angle_x': expected a horizontal field of view in (0, pi) "
                        f"radians, got {value!r}")
    return float(value)


#: Allowed deviation of a camera→world rotation part from orthonormal (``|RᵀR - I|``).
POSE_TOL = 1e-3


def _pose(meta_path: Path, i: int, value: object) -> torch.Tensor:
    """Frame ``i``'s ``transform_matrix`` as a float64 4×4 rigid camera→world matrix, or a
    :class:`DataError` naming the file, the frame and the field."""
    where = f"{meta_path}: frame {i}: field 'transform_matrix'"
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: expected a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise DataError(f"{where}: expected a 4x4 matrix, got shape {list(m.shape)}")
    if not np.isfinite(m).all():
        raise DataError(f"{where}: contains NaN or Inf")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DataError(f"{where}: expected last row [0, 0, 0, 1], got {m[3].tolist()}")
    R = m[:3, :3]
    if abs(np.linalg.det(R)) < 1e-6:
        raise DataError(f"{where}: the rotation part is singular (det {np.linalg.det(R):.3g})")
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if dev > POSE_TOL:
        raise DataError(f"{where}: the rotation part is not orthonormal (|RᵀR - I| = {dev:.3g} > {POSE_TOL:g}); "
                        f"expected a rigid camera-to-world pose")
    return torch.from_numpy(m)


def load_split(root: str | Path, split: str, *, resolution: int | Sequence[int] | None = None,
               background: Sequence[float] = (1.0, 1.0, 1.0), limit: int | None = None) -> PosedViews:
    """Load one split of a NeRF-synthetic scene.

    Args:
        root: scene folder holding ``transforms_<split>.json``.
        split: ``train``, ``val`` or ``test``.
        resolution: output size, ``W`` (square) or ``(W, H)``; ``None`` keeps the file size.
        background: RGB in [0, 1] composited under the RGBA images.
        limit: keep only the first ``limit`` frames (``None``: all).

    Returns:
        :class:`~nsplat.data.views.PosedViews` (float32, CPU; ``masks [B,H,W]`` the
        alpha coverage, ``background`` the composited colour).
    """
    root = Path(root)
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
    meta_path = root / f"transforms_{split}.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"root: no {meta_path.name} in {root}")
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{meta_path}: not valid JSON (truncated or corrupt?): {exc}") from exc
    if not isinstance(meta, dict) or "camera_angle_x" not in meta or "frames" not in meta:
        raise DataError(f"{meta_path}: expected keys 'camera_angle_x' and 'frames'")
    fov = _camera_angle(meta_path, meta["camera_angle_x"])
    if not isinstance(meta["frames"], list):
        raise DataError(f"{meta_path}: field 'frames': expected a list of frames, got {type(meta['frames']).__name__}")
    bg = torch.tensor([float(c) for c in background], dtype=torch.float32)
    if bg.shape != (3,) or bool(((bg < 0) | (bg > 1)).any()):
        raise ValueError(f"background: expected three values in [0, 1], got {list(background)}")
    frames = meta["frames"][:limit] if limit is not None else meta["frames"]
    if not frames:
        raise DataError(f"{meta_path}: no frames")
    rgba, c2w, names = [], [], []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise DataError(f"{meta_path}: frame {i} lacks 'file_path' or 'transform_matrix'")
        if not isinstance(fr["file_path"], str) or not fr["file_path"]:
            raise DataError(f"{meta_path}: frame {i}: field 'file_path': expected a non-empty string, "
                            f"got {fr['file_path']!r}")
        pose = _pose(meta_path, i, fr["transform_matrix"])
        img_path = _image_path(root, fr["file_path"])
        if not img_path.is_file():
            raise FileNotFoundError(f"{meta_path}: frame {i}: image file not found: {img_path}")
        try:
            img = iio.imread(img_path)
        except Exception as exc:  # noqa: BLE001 - any decoder failure means an unreadable image
            raise DataError(f"{img_path}: cannot read image (truncated or corrupt?): {exc}") from exc
        if img.ndim != 3 or img.shape[2] not in (3, 4):
            raise DataError(f"{img_path}: expected an RGB or RGBA image, got shape {img.shape}")
        img = img.astype(np.float32) / float(np.iinfo(img.dtype).max)
        if img.shape[2] == 3:
            img = np.concatenate([img, np.ones_like(img[..., :1])], -1)
        rgba.append(torch.from_numpy(img))
        c2w.append(pose)
        names.append(str(fr["file_path"]))
    if len({tuple(t.shape) for t in rgba}) != 1:
        raise DataError(f"{root}: images of split {split!r} differ in size")
    x = torch.stack(rgba)
    H0, W0 = x.shape[1:3]
    rgb, alpha = x[..., :3], x[..., 3:]
    x = torch.cat([rgb * alpha + bg * (1.0 - alpha), alpha], -1)
    if resolution is None:
        W, H = W0, H0
    elif isinstance(resolution, int):
        W = H = resolution
    else:
        W, H = (int(v) for v in resolution)
    if W < 1 or H < 1:
        raise ValueError(f"resolution: expected positive sizes, got {resolution}")
    x = _resize(x, (H, W))
    viewmats = opengl_c2w_to_viewmat(torch.stack(c2w))
    viewmats[:, 3, :] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=viewmats.dtype)  # exact after inverse
    Ks = intrinsics_from_fov(fov, W0, H0, batch=len(frames), dtype=torch.float64)
    Ks = scale_intrinsics(Ks, W / W0, H / H0)
    return PosedViews(images=x[..., :3].contiguous(), viewmats=viewmats.float(), Ks=Ks.float(), names=names,
                      masks=x[..., 3].contiguous(), background=bg)
