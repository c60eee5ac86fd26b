"""nsplat.ops — differentiable surface splatting via Poisson sampling (Müller et al., "Unbiased ...").

The default estimator ``"ht"`` is exactly unbiased with additive compositing; with alpha compositing no
estimator is (docs/op.md §4).

Public API:
    splat(...)          sampled EWA surface splatting (C++/OpenMP on CPU, CUDA on GPU)
    splat_dense(...)    exact dense oracle (pure PyTorch)
    splat_tiled(...)    every splat within a tolerance of its peak, tiled (ground truth at sparse cost)
    Splatter            nn.Module holding the op's settings
    SplatSettings       the op's settings as one value (Splatter's, and the render gateway's)
    sample(...)         per-pixel SPS sample (indices, inclusion probabilities, Λ̂)
    sampler_isa()       the CPU sampler's instruction set (NSPLAT_CPU_SIMD overrides; same bits on all)
    composite_sample(...) compositor of a given per-pixel sample (differentiable, estimator backward)
    diagnostics         Monte-Carlo bias/variance of the estimators against the dense oracle
    project(...)        differentiable EWA projection of surfels
"""
from .functional import composite_sample, sample, sampler_isa, splat
from .module import Splatter
from .output import SplatOutput
from .projection import ALPHA_MAX, Projected, project, tangent_frame
from .reference import splat_dense
from .settings import SplatSettings
from .tiled import splat_tiled

__all__ = ["Splatter", "SplatSettings", "splat", "sample", "sampler_isa", "composite_sample", "SplatOutput",
           "Projected", "project", "tangent_frame", "splat_dense", "splat_tiled", "ALPHA_MAX"]
