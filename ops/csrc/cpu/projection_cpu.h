// The EWA projection of oriented surfels on the CPU (projection_cpu.cpp): the model of ops/projection.py.
#pragma once
#include <torch/extension.h>

#include <vector>

#include "../core/projection.h"

namespace nsplat {

// means [N,3], normals [N,3], scales [N,2], opac [N], viewmats [B,4,4], Ks [B,3,3], one float dtype, contiguous.
// Returns {means2d [B,N,2], conics [B,N,3], amps, normals_cam [B,N,3], plane_offsets, depths, sigma2, valid (bool),
// hazard (int8: 1 a visible splat overflows the dtype, 2 a visible splat's det Sigma is in (0, 1e-20))}, [B,N] unless
// noted.
std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                        at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                        bool backface_cull);

// Gradients {means, normals, scales, opac, viewmats, Ks} given those of the first seven outputs of project_forward.
std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                         at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                         bool backface_cull, at::Tensor g_means2d, at::Tensor g_conics,
                                         at::Tensor g_amps, at::Tensor g_normals_cam, at::Tensor g_plane_offsets,
                                         at::Tensor g_depths, at::Tensor g_sigma2);

}  // namespace nsplat
