// Non-deterministic single-pass CPU backward of the compositor (scatter_cpu.cpp), bound in bindings.cpp.
#pragma once
#include <torch/extension.h>

#include <vector>

namespace nsplat {

// One pass over pixels: pass 1 of the backward (composite_backward_pixel) into thread-local slots,
// then every slot's gradient (splat_grad_entry) is scattered into the per-point buffers with OpenMP
// atomics. No entry sort, no [B,H,W,m] intermediates; the summation order depends on the thread
// schedule, so results agree with the deterministic two-pass backward only up to rounding.
// Returns {g_mu [B,N,2], g_con [B,N,3], g_amp [B,N], g_nrm [B,N,3], g_off [B,N], g_zc [B,N],
//          g_feat [N,C], bgw [B,H,W,1]}.
std::vector<at::Tensor> composite_backward_scatter(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                   at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor feat,
                                                   at::Tensor bg, at::Tensor indices, at::Tensor probs, int64_t mode,
                                                   int64_t estimator, at::Tensor g_img, at::Tensor g_alpha,
                                                   at::Tensor g_depth);

}  // namespace nsplat
