// CPU-only tiled render of every splat within a Mahalanobis radius (ops/tiled.py::splat_tiled).
#pragma once
#include <torch/extension.h>

#include <vector>

#include "../api.h"

namespace nsplat {

// {image [B,H,W,C], alpha [B,H,W,1], depth [B,H,W,1], weights}: per pixel, every splat with q(x) <= cutoff2 in
// (per-pixel depth, index) order, composited front to back (alpha mode) while the transmittance is >= t_stop.
// feat is [N,C] or [B,N,C]. weights: [B,N] each splat's compositing weights summed over the camera's pixels
// with point_weights, else empty.
std::vector<at::Tensor> render_tiled(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                                     at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor feat, at::Tensor bg,
                                     int64_t width, int64_t height, double cutoff2, double t_stop,
                                     bool point_weights);

}  // namespace nsplat
