// View-dependent colour on the CPU (view_colour_cpu.cpp): nsplat/sh.py's view_colour for degrees 1..3.
#pragma once
#include <torch/extension.h>

#include <vector>

namespace nsplat {

// feat [N, 3 (L+1)^2], means [N,3], viewmat [4,4], one float dtype, contiguous -> RGB [N,3].
at::Tensor view_colour_forward(at::Tensor feat, at::Tensor means, at::Tensor viewmat, int64_t degree);

// {g_feat, g_means, g_viewmat} given g_out [N,3].
std::vector<at::Tensor> view_colour_backward(at::Tensor feat, at::Tensor means, at::Tensor viewmat, int64_t degree,
                                             at::Tensor g_out);

}  // namespace nsplat
