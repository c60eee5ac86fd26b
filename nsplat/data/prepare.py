"""Downscaled copies of a NeRF-synthetic scene (``nsplat data prepare <scene> --resolution 400``; docs/data.md).

``<root>/nerf_synthetic/<scene>`` (800×800 RGBA; any of the eight scenes) → ``<root>/nerf_synthetic/<scene>_<N>``:
every frame image named in ``transforms_{train,val,test}.json`` is area-averaged to ``N`` pixels wide (height in
proportion) on premultiplied colour, so that compositing the result over any background equals area-averaging the
composited original; the transforms are copied unchanged (``camera_angle_x`` does not depend on the size).
The output is written to ``<scene>_<N>.part`` and renamed into place, so it is complete or absent.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from nsplat.data.archives import FetchError, check_scene, scene_frames
from nsplat.data.fetch import write_error
from nsplat.data.nerf_synthetic import SPLITS


def area_downscale_rgba(image: np.ndarray, width: int) -> np.ndarray:
    """Area-average an ``[H,W,3|4]`` uint8 image to ``width`` pixels wide (height in proportion), averaging
    premultiplied colour; returns uint8 with the input's channels."""
    H, W, C = image.shape
    size = (max(1, round(H * width / W)), width)
    x = torch.from_numpy(image).to(torch.float64) / 255.0
    if C == 4:
        x = torch.cat([x[..., :3] * x[..., 3:], x[..., 3:]], -1)
    y = F.interpolate(x.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0)
    if C == 4:
        alpha = y[..., 3:]
        y = torch.cat([torch.where(alpha > 0, y[..., :3] / alpha.clamp_min(1e-12), 0.0), alpha], -1)
    return (y.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()


def _downscale_file(src: Path, dst: Path, width: int) -> None:
    """Read one frame image, downscale it and write it as PNG."""
    try:
        image = iio.imread(src)
    except (OSError, ValueError) as exc:
        raise FetchError(f"{src}: not a readable image ({exc})") from None
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
        raise FetchError(f"{src}: expected an 8-bit RGB or RGBA image, got shape {list(image.shape)} {image.dtype}")
    if width > image.shape[1]:
        raise FetchError(f"--resolution {width}: larger than the source images ({image.shape[1]} px wide)")
    dst.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(dst, area_downscale_rgba(image, width), extension=".png")


def prepare(src: Path, resolution: int, *, progress: bool = True) -> tuple[Path, bool]:
    """Write ``<src>_<resolution>`` from the scene folder ``src``; returns it and whether it was already there."""
    if resolution < 1:
        raise FetchError(f"--resolution: expected a positive number of pixels, got {resolution}")
    dest = src.with_name(f"{src.name}_{resolution}")
    if dest.exists():
        check_scene(dest, str(dest))
        return dest, True
    if not src.is_dir():
        raise FetchError(f"no scene at {src} to downscale; fetch it first (nsplat data fetch {src.name})")
    images = scene_frames(src, str(src))
    stage = dest.with_name(dest.name + ".part")
    try:
        shutil.rmtree(stage, ignore_errors=True)  # left by a killed run
        stage.mkdir()
        for rel in tqdm(images, desc=dest.name, unit="image", disable=None if progress else True,
                        leave=False):
            _downscale_file(src / rel, stage / rel, resolution)
        for split in SPLITS:
            shutil.copyfile(src / f"transforms_{split}.json", stage / f"transforms_{split}.json")
        os.replace(stage, dest)
    except OSError as exc:
        raise write_error(exc, dest.parent) from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return dest, False
