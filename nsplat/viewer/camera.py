"""Browser camera ↔ library camera.

viser reports a client's camera as an OpenCV camera→world pose (``wxyz`` quaternion, ``position``),
a vertical field of view (radians) and the canvas aspect (width / height); the library uses OpenCV
world→camera ``viewmats [4,4]`` and pixel intrinsics ``K [3,3]``.
"""
from __future__ import annotations

import math
from typing import Protocol

import numpy as np
import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

from nsplat.cameras import intrinsics


class CameraLike(Protocol):
    """What a viser ``CameraHandle`` offers (and what tests fake)."""

    wxyz: np.ndarray
    position: np.ndarray
    fov: float
    aspect: float


def image_size(aspect: float, resolution: int) -> tuple[int, int]:
    """``(width, height)`` with the longest side ``resolution`` and the given aspect (width / height)."""
    if aspect >= 1.0:
        return resolution, max(8, round(resolution / aspect))
    return max(8, round(resolution * aspect)), resolution


def viewmat_from_pose(wxyz: np.ndarray | torch.Tensor, position: np.ndarray | torch.Tensor) -> torch.Tensor:
    """OpenCV world→camera ``[4,4]`` (float64) of a camera→world pose (quaternion ``wxyz [4]``, ``position [3]``)."""
    q = torch.as_tensor(np.asarray(wxyz, dtype=np.float64))
    R = quaternion_to_rotation_matrix(q / q.norm())
    t = torch.as_tensor(np.asarray(position, dtype=np.float64))
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R.T
    V[:3, 3] = -R.T @ t
    return V


def pose_from_viewmat(viewmat: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(wxyz [4], position [3])`` camera→world pose of an OpenCV world→camera ``viewmat [4,4]``."""
    V = viewmat.detach().double().cpu()
    R = V[:3, :3]
    q = rotation_matrix_to_quaternion(R.T.contiguous())
    position = -R.T @ V[:3, 3]
    return q.numpy(), position.numpy()


def intrinsics_from_vfov(fov_y: float, width: int, height: int) -> torch.Tensor:
    """``[3,3]`` centred square-pixel intrinsics for a vertical field of view ``fov_y`` (radians)."""
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return intrinsics(f, f, 0.5 * width, 0.5 * height, dtype=torch.float64)[0]


def vfov_of(K: torch.Tensor, height: int) -> float:
    """Vertical field of view (radians) of intrinsics ``K [3,3]`` for an image ``height`` pixels high."""
    return 2.0 * math.atan(0.5 * height / float(K[1, 1]))


def camera_request(camera: CameraLike, resolution: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """``(viewmat [4,4], K [3,3], width, height)`` of a browser camera at the given longest side."""
    width, height = image_size(float(camera.aspect), resolution)
    return (viewmat_from_pose(camera.wxyz, camera.position), intrinsics_from_vfov(float(camera.fov), width, height),
            width, height)
