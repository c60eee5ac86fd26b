"""Lambert shading of per-point albedo under camera-relative directional lights.

The paper's shape-reconstruction setting (after DSS): three directional lights fixed to the camera — a
red headlight, a green light from above and a blue light from below — each of intensity ``0.9·π``.
With the Lambert BRDF ``albedo/π`` the outgoing radiance of channel ``c`` at a point with camera-space
unit normal ``n`` is

    L_c = albedo_c · Σ_l (I_l / π) · colour_{l,c} · max(0, n · ω_l)

where ``ω_l`` is the camera-space unit direction towards light ``l`` (OpenCV camera: x right, y down,
z forward, so the headlight direction is ``(0, 0, -1)``, "above" is ``(0, -1, 0)``, "below" ``(0, 1, 0)``).

Because the lights move with the camera, the shaded colour depends on the camera: :func:`lambert`
returns one feature tensor per camera ``[B, N, C]``, which the op takes as per-camera features (one call for
all cameras, :func:`nsplat.render.renderer.render_views`).
"""
from __future__ import annotations

import dataclasses
import math

import torch


@dataclasses.dataclass(frozen=True)
class DirectionalLight:
    """A light fixed to the camera.

    Attributes:
        direction: camera-space direction *towards* the light (normalised on use).
        colour: RGB colour (per channel multiplier).
        intensity: radiant intensity; the Lambert BRDF divides it by π.
    """

    direction: tuple[float, float, float]
    colour: tuple[float, float, float]
    intensity: float = 0.9 * math.pi


#: The paper's lights: red headlight, green from above, blue from below (OpenCV camera axes).
PAPER_LIGHTS: tuple[DirectionalLight, ...] = (
    DirectionalLight((0.0, 0.0, -1.0), (1.0, 0.0, 0.0)),
    DirectionalLight((0.0, -1.0, 0.0), (0.0, 1.0, 0.0)),
    DirectionalLight((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
)


def light_matrix(lights: tuple[DirectionalLight, ...], dtype: torch.dtype = torch.float32,
                 device: str | torch.device = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """``(directions [L,3] unit, radiance_scale [L,3] = I/π · colour)`` of ``lights``."""
    d = torch.tensor([light.direction for light in lights], dtype=dtype, device=device)
    d = torch.nn.functional.normalize(d, dim=-1)
    c = torch.tensor([[light.intensity / math.pi * x for x in light.colour] for light in lights], dtype=dtype,
                     device=device)
    return d, c


def lambert(albedo: torch.Tensor, normals: torch.Tensor, viewmats: torch.Tensor,
            lights: tuple[DirectionalLight, ...] = PAPER_LIGHTS) -> torch.Tensor:
    """Shaded colour of every point seen from every camera.

    Args:
        albedo: ``[N,3]`` per-point albedo (RGB).
        normals: ``[N,3]`` world-space unit normals.
        viewmats: ``[B,4,4]`` world→camera (OpenCV); only the rotation is used.
        lights: camera-relative directional lights (default: the paper's).

    Returns:
        ``[B,N,3]`` radiance per camera and point; differentiable w.r.t. albedo, normals and viewmats.
    """
    if albedo.dim() != 2 or albedo.shape[1] != 3:
        raise ValueError(f"albedo: expected shape [N, 3], got {list(albedo.shape)}")
    if normals.shape != (albedo.shape[0], 3):
        raise ValueError(f"normals: expected shape [{albedo.shape[0]}, 3], got {list(normals.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats: expected shape [B, 4, 4], got {list(viewmats.shape)}")
    dirs, rad = light_matrix(lights, albedo.dtype, albedo.device)
    n_cam = torch.einsum("bij,nj->bni", viewmats[:, :3, :3], normals)      # [B,N,3]
    cosines = torch.clamp(n_cam @ dirs.T, min=0.0)                          # [B,N,L]
    irradiance = cosines @ rad                                              # [B,N,3]
    return albedo[None] * irradiance
