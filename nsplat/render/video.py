"""Videos of a camera path: what the ``render`` command was asked for (:class:`RenderRequest`), the picture
of each output (RGB, depth, normal, alpha) and the writer (mp4 through imageio's ffmpeg plugin, else a PNG
sequence with a note).

Pictures (``uint8 [T,H,W,3]``):

* ``rgb``: the model's colour;
* ``depth``: the alpha-normalised camera depth through matplotlib's ``turbo`` colour map, between the 2nd and
  98th percentile of the covered pixels of the whole video (one scale for all frames), black where empty;
* ``normal``: the surface normal in camera coordinates with OpenGL's axes (x right, y up, z towards the
  viewer), turned to face the camera, as ``(n + 1) / 2`` (a surface facing the camera is ``(0.5, 0.5, 1)``),
  on black where empty;
* ``alpha``: the coverage as grey.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import imageio
import imageio.v3 as iio
import numpy as np
import torch
from matplotlib import colormaps

log = logging.getLogger(__name__)

#: Outputs the ``render`` command writes, in this order.
OUTPUTS = ("rgb", "depth", "normal", "alpha")
#: Named paths (anything else is a nerfstudio ``camera_path.json`` file).
PATHS = ("orbit", "test", "train-smooth")


@dataclasses.dataclass
class RenderRequest:
    """The ``render`` command's options.

    Attributes:
        path: ``orbit``, ``test`` (the held-out views in order), ``train-smooth`` (a smooth path through the
            training cameras) or a nerfstudio ``camera_path.json`` file (relative: to the current folder).
        outputs: any of ``rgb``, ``depth``, ``normal``, ``alpha``; one video each.
        fps: frame rate (``None``: the camera path file's, else the config's).
        frames: frames of ``orbit`` and ``train-smooth`` (``None``: the config's).
        resolution: longest image side in pixels (``None``: the training images' size, or the file's).
    """

    path: str = "orbit"
    outputs: tuple[str, ...] = ("rgb",)
    fps: float | None = None
    frames: int | None = None
    resolution: int | None = None

    def __post_init__(self) -> None:
        bad = [o for o in self.outputs if o not in OUTPUTS]
        if bad or not self.outputs:
            what = f"unknown output {bad[0]!r} in {','.join(self.outputs)}" if bad else "no output named"
            raise ValueError(f"--outputs: {what}; expected a comma-separated subset of {','.join(OUTPUTS)}")
        if self.path not in PATHS and not self.path.endswith(".json"):
            raise ValueError(f"--path: expected one of {', '.join(PATHS)} or a nerfstudio camera_path .json file, "
                             f"got {self.path!r}")
        for name, value in (("fps", self.fps), ("frames", self.frames), ("resolution", self.resolution)):
            if value is not None and not (value > 0 and math.isfinite(value)):
                raise ValueError(f"--{name}: expected a positive finite number, got {value}")

    @property
    def name(self) -> str:
        """Stem of the written videos: the path's name, or the camera path file's stem."""
        return self.path if self.path in PATHS else Path(self.path).stem


def to_uint8(x: torch.Tensor) -> np.ndarray:
    """``[..., 3]`` values in [0, 1] → uint8 (rounded)."""
    return (x.detach().float().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def depth_picture(depth: torch.Tensor, alpha: torch.Tensor) -> np.ndarray:
    """``[T,H,W,3]`` uint8 of normalised depth ``[T,H,W,1]`` and coverage ``alpha [T,H,W,1]`` (module docstring)."""
    d, covered = depth[..., 0].float().cpu(), alpha[..., 0].cpu() > 0.5
    if not bool(covered.any()):
        return np.zeros((*d.shape, 3), np.uint8)
    vals = d[covered]
    lo, hi = torch.quantile(vals, 0.02), torch.quantile(vals, 0.98)
    t = ((d - lo) / (hi - lo).clamp_min(1e-8)).clamp(0, 1).numpy()
    pic = (colormaps["turbo"](t)[..., :3] * 255.0 + 0.5).astype(np.uint8)
    pic[~covered.numpy()] = 0
    return pic


def normal_picture(normals: torch.Tensor, alpha: torch.Tensor) -> np.ndarray:
    """``[T,H,W,3]`` uint8 of camera-space (OpenCV) unit normals ``[T,H,W,3]`` facing the camera, on black by
    coverage ``alpha [T,H,W,1]`` (module docstring)."""
    gl = normals * torch.tensor([1.0, -1.0, -1.0], dtype=normals.dtype, device=normals.device)
    return to_uint8(0.5 * (gl + 1.0) * alpha.clamp(0, 1))


def write_video(frames: np.ndarray, path: Path, fps: float) -> Path:
    """Write ``frames [T,H,W,3]`` uint8 as an H.264 mp4 at ``path`` (sizes padded to even numbers by repeating
    the last row/column, as yuv420p needs); without an ffmpeg backend (``imageio-ffmpeg``), a PNG sequence
    ``<path without .mp4>/frame_00000.png …`` instead, with a note in the log. Returns what was written."""
    H, W = frames.shape[1:3]
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as exc:
        folder = path.with_suffix("")
        folder.mkdir(parents=True, exist_ok=True)
        for i, frame in enumerate(frames):
            iio.imwrite(folder / f"frame_{i:05d}.png", frame)
        log.warning("no ffmpeg backend for imageio (%s): wrote %d PNG frames to %s instead of %s "
                    "(pip install imageio-ffmpeg)", " ".join(str(exc).split()), len(frames), folder, path.name)
        return folder
    padded = np.pad(frames, ((0, 0), (0, H % 2), (0, W % 2), (0, 0)), mode="edge")
    imageio.mimwrite(path, list(padded), fps=fps, macro_block_size=1)
    return path
