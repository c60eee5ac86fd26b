"""Cameras in the library's convention: OpenCV (x right, y down, z forward), world→camera 4×4
``viewmats`` and pixel intrinsics ``Ks``. Other conventions are converted here, once."""
from __future__ import annotations

import math

import torch
from kornia.geometry.liegroup import So3

#: Flips y and z: OpenGL/Blender camera axes (x right, y up, z backward) ↔ OpenCV.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


def intrinsics(fx: float, fy: float, cx: float, cy: float, batch: int = 1,
               dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu") -> torch.Tensor:
    """``[batch, 3, 3]`` pinhole intrinsics in pixels."""
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device)
    return K.expand(batch, 3, 3).clone()


def intrinsics_from_fov(fov_x: float, width: int, height: int, batch: int = 1,
                        dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu") -> torch.Tensor:
    """Intrinsics ``[batch,3,3]`` for a horizontal field of view (radians), square pixels, centred."""
    f = 0.5 * width / math.tan(0.5 * fov_x)
    return intrinsics(f, f, 0.5 * width, 0.5 * height, batch, dtype, device)


def scale_intrinsics(Ks: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """Intrinsics of an image resized by ``(sx, sy)`` (pixel-centre convention preserved)."""
    S = torch.diag(torch.tensor([sx, sy, 1.0], dtype=Ks.dtype, device=Ks.device))
    return S @ Ks


def opengl_c2w_to_viewmat(c2w: torch.Tensor) -> torch.Tensor:
    """NeRF/Blender camera→world (OpenGL axes) ``[...,4,4]`` → OpenCV world→camera ``[...,4,4]``."""
    flip = _GL_TO_CV.to(dtype=c2w.dtype, device=c2w.device)
    return torch.linalg.inv(c2w @ flip)


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """OpenCV world→camera matrices ``[B,4,4]`` for cameras at ``eye [B,3]`` looking at ``target [B,3]``.

    ``up [3]`` or ``[B,3]`` is the world up direction (image y points opposite to it).
    """
    eye, target = torch.atleast_2d(eye), torch.atleast_2d(target)
    up = torch.atleast_2d(up).to(eye).expand_as(eye)
    z = torch.nn.functional.normalize(target - eye, dim=-1)
    x = torch.nn.functional.normalize(torch.cross(z, up, dim=-1), dim=-1)
    y = torch.cross(z, x, dim=-1)
    R = torch.stack([x, y, z], dim=1)
    V = torch.eye(4, dtype=eye.dtype, device=eye.device).repeat(eye.shape[0], 1, 1)
    V[:, :3, :3] = R
    V[:, :3, 3] = -(R @ eye[..., None])[..., 0]
    return V


def sphere_views(count: int, radius: float, seed: int = 0, dtype: torch.dtype = torch.float32,
                 target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> torch.Tensor:
    """``[count,4,4]`` cameras at uniformly random directions on a sphere, looking at ``target``."""
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(count, 3, generator=g, dtype=torch.float64), dim=-1)
    t = torch.tensor(target, dtype=torch.float64)
    eye = t + radius * d
    up = torch.where((d[:, 2:].abs() > 0.99), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                     torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    return look_at(eye, t.expand_as(eye), up).to(dtype)


def perturb_viewmats(viewmats: torch.Tensor, rot_deg: float, trans: float,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """Perturb cameras ``[B,4,4]`` by random rotations of exactly ``rot_deg`` degrees (random axes,
    about the camera centre) and random camera-centre offsets of exactly length ``trans``.

    Returns the perturbed world→camera matrices ``[B,4,4]`` (same dtype/device).
    """
    B = viewmats.shape[0]
    dt = torch.float64
    axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=generator, dtype=dt), dim=-1)
    dirs = torch.nn.functional.normalize(torch.randn(B, 3, generator=generator, dtype=dt), dim=-1)
    dR = So3.exp(axis * math.radians(rot_deg)).matrix()
    V = viewmats.detach().to(dt).cpu()
    R, t = V[:, :3, :3], V[:, :3, 3]
    centre = -(R.transpose(1, 2) @ t[..., None])[..., 0] + trans * dirs
    R2 = dR @ R
    out = torch.eye(4, dtype=dt).repeat(B, 1, 1)
    out[:, :3, :3] = R2
    out[:, :3, 3] = -(R2 @ centre[..., None])[..., 0]
    return out.to(viewmats)


def camera_centres(viewmats: torch.Tensor) -> torch.Tensor:
    """World positions ``[B, 3]`` of the optical centres of world→camera matrices ``[B,4,4]``."""
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
    return -(R.transpose(1, 2) @ t[..., None])[..., 0]


def look_at_point(viewmats: torch.Tensor) -> tuple[torch.Tensor, float]:
    """``(point [3] float64, spread)``: the point nearest (least squares) to the optical axes of
    ``viewmats [V,4,4]`` and the smallest eigenvalue of the mean projector ``I − a aᵀ`` (how well the axes
    pin it down)."""
    C = camera_centres(viewmats.double())
    axis = viewmats[:, 2, :3].double()
    P = torch.eye(3, dtype=torch.float64) - axis[:, :, None] * axis[:, None, :]
    point = torch.linalg.lstsq(P.sum(0), (P @ C[:, :, None]).sum(0)).solution[:, 0]
    return point, float(torch.linalg.eigvalsh(P.mean(0))[0])
