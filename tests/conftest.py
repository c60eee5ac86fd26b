"""Shared fixtures: small seeded surfel scenes and cameras in the library's conventions."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

torch.set_num_threads(2)


def make_scene(N: int, seed: int, C: int = 3, dtype: torch.dtype = torch.float64, spread: float = 0.5,
               scale: tuple[float, float] = (0.04, 0.15)) -> dict[str, torch.Tensor]:
    """Random surfels in a cube of half-size ``spread`` around the origin, normals roughly towards -z."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(N, 3, generator=g, dtype=dtype) - 0.5) * 2 * spread
    normals = torch.randn(N, 3, generator=g, dtype=dtype) * 0.5
    normals[:, 2] = -normals[:, 2].abs() - 0.5
    scales = scale[0] + (scale[1] - scale[0]) * torch.rand(N, 2, generator=g, dtype=dtype)
    opacities = 0.3 + 0.6 * torch.rand(N, generator=g, dtype=dtype)
    features = torch.rand(N, C, generator=g, dtype=dtype)
    return dict(means=means, normals=normals, scales=scales, opacities=opacities, features=features)


def make_cameras(B: int, width: int, height: int, dtype: torch.dtype = torch.float64, dist: float = 2.5,
                 focal: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``B`` cameras on a small arc around the origin looking down +z (OpenCV), and their intrinsics."""
    viewmats = torch.zeros(B, 4, 4, dtype=dtype)
    for b in range(B):
        a = 0.15 * b
        R = torch.tensor([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]],
                         dtype=dtype)
        viewmats[b, :3, :3] = R
        viewmats[b, :3, 3] = torch.tensor([0.02 * b, -0.01 * b, dist], dtype=dtype)
        viewmats[b, 3, 3] = 1.0
    f = focal if focal is not None else 1.1 * max(width, height)
    Ks = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype).repeat(B, 1, 1)
    return viewmats, Ks


def write_dss_ply(path: Path, points: int = 600, seed: int = 0) -> Path:
    """A small DSS-style point cloud at ``path``: binary little-endian PLY with float ``x y z nx ny nz``
    vertices and an empty ``face`` element, as the published DSS files (``dss_pointclouds/*.ply``).
    The points lie on a slightly squashed unit-size ellipsoid with its outward normals."""
    g = np.random.default_rng(seed)
    d = g.normal(size=(points, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    axes = np.array([0.5, 0.4, 0.45])
    xyz = d * axes
    nrm = d / axes
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    vertex = np.empty(points, dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for i, k in enumerate("xyz"):
        vertex[k], vertex[f"n{k}"] = xyz[:, i], nrm[:, i]
    face = np.empty(0, dtype=[("vertex_indices", "O")])
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face",
                                                                        val_types={"vertex_indices": "i4"},
                                                                        len_types={"vertex_indices": "u1"})],
            text=False, byte_order="<").write(str(path))
    return path


@pytest.fixture
def scene_factory():
    return make_scene


@pytest.fixture
def camera_factory():
    return make_cameras
