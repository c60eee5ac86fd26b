// The native API both backends export, declared once: the CPU backend defines these functions in
// cpu/splat_cpu.cpp, the CUDA backend in cuda/bindings.cpp (checks, then the launchers in splat_cuda.cu).
// Each backend's bindings.cpp binds them under the same names; ops/library.py calls them through the
// registered custom ops. Tensors are contiguous and of one float dtype (float32/float64) per call except
// Ks [B,3,3] (made double inside), indices int32, entries/seg int64.
#pragma once
#include <torch/extension.h>

#include <string>
#include <vector>

namespace nsplat {

// feat is [N,C] or [B,N,C] for the B cameras and N points of amp [B,N].
inline void check_features(const at::Tensor& feat, const at::Tensor& amp) {
  const bool shared = feat.dim() == 2 && feat.size(0) == amp.size(1);
  const bool per_camera = feat.dim() == 3 && feat.size(0) == amp.size(0) && feat.size(1) == amp.size(1);
  TORCH_CHECK(shared || per_camera, "nsplat: features must be [N, C] or [B, N, C] with B = ", amp.size(0), " and N = ",
              amp.size(1), ", got ", feat.sizes());
}

// Camera b's features: feat [N,C] (every camera's) or [B,N,C] (row b), as a pointer to its [N,C] block.
template <typename S>
inline const S* camera_features(const at::Tensor& feat, int64_t b) {
  return feat.data_ptr<S>() + (feat.dim() == 3 ? b * feat.size(1) * feat.size(2) : 0);
}

// The sampler's per-camera random streams: an int64 CPU tensor [B,2] of (seed, camera) pairs.
inline void check_streams(const at::Tensor& streams, int64_t B) {
  TORCH_CHECK(streams.device().is_cpu() && streams.scalar_type() == at::kLong && streams.dim() == 2 &&
                  streams.size(0) == B && streams.size(1) == 2 && streams.is_contiguous(),
              "nsplat: streams must be a contiguous int64 CPU tensor [B,2] of (seed, camera), B = ", B);
}

// Per-pixel SPS sample: {indices [B,H,W,m] int32, probs [B,H,W,m], total [B,H,W,1], work [B,H,W,1] int32}.
// streams [B,2] int64 (CPU): camera b draws u(seed, camera, pixel, point) with (seed, camera) = streams[b].
std::vector<at::Tensor> sample(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                               at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor streams, int64_t width,
                               int64_t height, int64_t samples, double eps, int64_t order, double tol,
                               int64_t inclusion, bool stratified);

// Compositing of a given sample: {image [B,H,W,C], alpha [B,H,W,1], depth [B,H,W,1]}. feat is [N,C] (every camera
// sees the same features) or [B,N,C] (camera b sees feat[b]: view-dependent features).
std::vector<at::Tensor> composite_forward(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm, at::Tensor off,
                                          at::Tensor zc, at::Tensor Ks, at::Tensor feat, at::Tensor bg,
                                          at::Tensor indices, at::Tensor probs, int64_t mode);

// Backward pass 1, per pixel: {dalpha [B,H,W,m], wf [B,H,W,m], bgw [B,H,W,1]}.
std::vector<at::Tensor> composite_backward_pixels(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                  at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor feat,
                                                  at::Tensor bg, at::Tensor indices, at::Tensor probs, int64_t mode,
                                                  int64_t estimator, at::Tensor g_img, at::Tensor g_alpha,
                                                  at::Tensor g_depth);

// Backward pass 2, per point in the (point, camera, slot) order of entries/seg:
// {g_mu [B,N,2], g_con [B,N,3], g_amp [B,N], g_nrm [B,N,3], g_off [B,N], g_zc [B,N], g_feat}, g_feat [N,C] summed
// over the cameras, or [B,N,C] with per_camera_features (the features were [B,N,C]).
std::vector<at::Tensor> composite_backward_points(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                  at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor entries,
                                                  at::Tensor seg, at::Tensor dalpha, at::Tensor wf, at::Tensor g_img,
                                                  at::Tensor g_depth, int64_t width, int64_t height,
                                                  int64_t estimator, bool per_camera_features);

// CPU only (cpu/splat_cpu.cpp): the sampler's instruction set for `name` ("auto" or one of sampler_isas(); the
// environment variable NSPLAT_CPU_SIMD overrides "auto"), and the instruction sets of this build.
std::string sampler_isa(std::string name);
std::vector<std::string> sampler_isas();

// CPU only (cpu/splat_cpu.cpp): filled slots grouped by point, stable counting sort: {entries [E], seg [N+1]}.
std::vector<at::Tensor> entries_by_point(at::Tensor indices, int64_t num_points);

}  // namespace nsplat
