"""nsplat.ops — unbiased differentiable surface splatting via Poisson sampling.

Public API:
    splat(...)          sampled EWA surface splatting (C++/OpenMP on CPU, CUDA on GPU)
    splat_dense(...)    exact dense oracle (pure PyTorch)
    Splatter            nn.Module holding the op's settings
    composite(...)      compositor of a given per-pixel sample (differentiable)
    project(...)        differentiable EWA projection of surfels
"""
from .output import SplatOutput
from .projection import ALPHA_MAX, Projected, project, tangent_frame
from .reference import splat_dense

__all__ = ["SplatOutput", "Projected", "project", "tangent_frame", "splat_dense", "ALPHA_MAX"]
