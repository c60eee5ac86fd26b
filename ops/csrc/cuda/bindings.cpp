// Python bindings of the CUDA backend: argument checks, then the launchers in splat_cuda.cu.
//
// The module exposes the four functions of the shared API (../api.h) and the projection and view colour that the
// CPU module also exposes (cpu/bindings.cpp), with the same signatures and semantics; ops/library.py's CUDA
// kernels call it.
#include <torch/extension.h>

#include "../api.h"

#include <limits>
#include <vector>

namespace nsplat {

// splat_cuda.cu
int64_t host_reads_cuda();  // reads of device values by the host so far (launch.h, to_host)
#if defined(NSPLAT_CUDA_EMULATE)
std::vector<at::Tensor> merge_lanes_emulated(const at::Tensor& key, const at::Tensor& idx, const at::Tensor& cnt,
                                             int64_t m);
int64_t launches_emulated();
#endif
std::vector<at::Tensor> sample_cuda(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp,
                                    const at::Tensor& sig2, const at::Tensor& nrm, const at::Tensor& off,
                                    const at::Tensor& zc, const at::Tensor& Ks, const at::Tensor& streams,
                                    int64_t width, int64_t height, int64_t samples, double eps, int64_t order,
                                    double tol, int64_t inclusion, bool stratified);
std::vector<at::Tensor> composite_forward_cuda(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp,
                                               const at::Tensor& nrm, const at::Tensor& off, const at::Tensor& zc,
                                               const at::Tensor& Ks, const at::Tensor& feat, const at::Tensor& bg,
                                               const at::Tensor& indices, const at::Tensor& probs, int64_t mode);
std::vector<at::Tensor> composite_backward_pixels_cuda(const at::Tensor& mu, const at::Tensor& con,
                                                       const at::Tensor& amp, const at::Tensor& nrm,
                                                       const at::Tensor& off, const at::Tensor& zc,
                                                       const at::Tensor& Ks, const at::Tensor& feat,
                                                       const at::Tensor& bg, const at::Tensor& indices,
                                                       const at::Tensor& probs, int64_t mode, int64_t estimator,
                                                       const at::Tensor& g_img, const at::Tensor& g_alpha,
                                                       const at::Tensor& g_depth);
std::vector<at::Tensor> composite_backward_points_cuda(const at::Tensor& mu, const at::Tensor& con,
                                                       const at::Tensor& amp, const at::Tensor& nrm,
                                                       const at::Tensor& off, const at::Tensor& zc,
                                                       const at::Tensor& Ks, const at::Tensor& entries,
                                                       const at::Tensor& seg, const at::Tensor& dalpha,
                                                       const at::Tensor& wf, const at::Tensor& g_img,
                                                       const at::Tensor& g_depth, int64_t width, int64_t height,
                                                       int64_t estimator, bool per_camera_features);

// projection_cuda.cu
std::vector<at::Tensor> project_forward_cuda(const at::Tensor& means, const at::Tensor& normals,
                                             const at::Tensor& scales, const at::Tensor& opac,
                                             const at::Tensor& viewmats, const at::Tensor& Ks, double near, double far,
                                             double lowpass, bool backface_cull);
std::vector<at::Tensor> project_backward_cuda(const at::Tensor& means, const at::Tensor& normals,
                                              const at::Tensor& scales, const at::Tensor& opac,
                                              const at::Tensor& viewmats, const at::Tensor& Ks, double near,
                                              double far, double lowpass, bool backface_cull,
                                              const std::vector<at::Tensor>& g);
at::Tensor view_colour_forward_cuda(const at::Tensor& feat, const at::Tensor& means, const at::Tensor& viewmat,
                                    int64_t degree);
std::vector<at::Tensor> view_colour_backward_cuda(const at::Tensor& feat, const at::Tensor& means,
                                                  const at::Tensor& viewmat, int64_t degree, const at::Tensor& g_out);

namespace {

// Every tensor on the CUDA device of the first one, and contiguous. (The host emulation build used by the
// tests, emulate.cpp, takes CPU tensors instead.)
void check_cuda(const std::vector<at::Tensor>& ts) {
  const auto device = ts.front().device();
  for (const auto& t : ts) {
#if defined(NSPLAT_CUDA_EMULATE)
    TORCH_CHECK(t.device().is_cpu(), "nsplat CUDA emulation got a tensor on ", t.device());
#else
    TORCH_CHECK(t.is_cuda(), "nsplat CUDA backend got a tensor on ", t.device());
#endif
    TORCH_CHECK(t.device() == device, "nsplat CUDA backend: tensors on ", device, " and ", t.device());
    TORCH_CHECK(t.is_contiguous(), "nsplat CUDA backend expects contiguous tensors");
  }
}

// Working-precision tensors share the dtype of the first one (float32 or float64); Ks may differ (made double).
void check_dtype(const std::vector<at::Tensor>& ts) {
  const auto dtype = ts.front().scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "nsplat CUDA backend: expected float32 or float64, got ",
              dtype);
  for (const auto& t : ts)
    TORCH_CHECK(t.scalar_type() == dtype, "nsplat CUDA backend: expected dtype ", dtype, ", got ", t.scalar_type());
}

void check_points(const at::Tensor& amp) {
  TORCH_CHECK(amp.dim() == 2, "nsplat CUDA backend: amps must be [B, N]");
  TORCH_CHECK(amp.size(1) < std::numeric_limits<int>::max(), "nsplat CUDA backend: N must be below 2^31");
}

}  // namespace

std::vector<at::Tensor> sample(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                               at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor streams, int64_t width,
                               int64_t height, int64_t samples, double eps, int64_t order, double tol,
                               int64_t inclusion, bool stratified) {
  check_cuda({mu, con, amp, sig2, nrm, off, zc, Ks});
  check_streams(streams, amp.size(0));
  check_dtype({mu, con, amp, sig2, nrm, off, zc});
  check_points(amp);
  TORCH_CHECK(width >= 1 && height >= 1, "nsplat: width and height must be >= 1");
  TORCH_CHECK(samples >= 1 && samples < std::numeric_limits<int>::max(), "nsplat: samples must be in [1, 2^31)");
  TORCH_CHECK(eps > 0 && eps <= 1, "nsplat: eps must be in (0, 1]");
  TORCH_CHECK(order >= 0 && order <= 16, "nsplat: hermite_order must be in [0, 16]");
  TORCH_CHECK(inclusion == 0 || inclusion == 1, "nsplat: inclusion must be 0 (threshold) or 1 (pips)");
  return sample_cuda(mu, con, amp, sig2, nrm, off, zc, Ks, streams, width, height, samples, eps, order, tol,
                     inclusion, stratified);
}

std::vector<at::Tensor> composite_forward(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm, at::Tensor off,
                                          at::Tensor zc, at::Tensor Ks, at::Tensor feat, at::Tensor bg,
                                          at::Tensor indices, at::Tensor probs, int64_t mode) {
  check_cuda({mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs});
  check_dtype({mu, con, amp, nrm, off, zc, feat, bg, probs});
  check_features(feat, amp);
  check_points(amp);
  TORCH_CHECK(indices.scalar_type() == at::kInt && indices.dim() == 4, "nsplat: indices must be int32 [B,H,W,m]");
  return composite_forward_cuda(mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, mode);
}

std::vector<at::Tensor> composite_backward_pixels(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                  at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor feat,
                                                  at::Tensor bg, at::Tensor indices, at::Tensor probs, int64_t mode,
                                                  int64_t estimator, at::Tensor g_img, at::Tensor g_alpha,
                                                  at::Tensor g_depth) {
  check_cuda({mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, g_img, g_alpha, g_depth});
  check_dtype({mu, con, amp, nrm, off, zc, feat, bg, probs, g_img, g_alpha, g_depth});
  check_features(feat, amp);
  check_points(amp);
  TORCH_CHECK(indices.scalar_type() == at::kInt && indices.dim() == 4, "nsplat: indices must be int32 [B,H,W,m]");
  return composite_backward_pixels_cuda(mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, mode, estimator,
                                        g_img, g_alpha, g_depth);
}

std::vector<at::Tensor> composite_backward_points(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                  at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor entries,
                                                  at::Tensor seg, at::Tensor dalpha, at::Tensor wf, at::Tensor g_img,
                                                  at::Tensor g_depth, int64_t width, int64_t height,
                                                  int64_t estimator, bool per_camera_features) {
  check_cuda({mu, con, amp, nrm, off, zc, Ks, entries, seg, dalpha, wf, g_img, g_depth});
  check_dtype({mu, con, amp, nrm, off, zc, dalpha, wf, g_img, g_depth});
  check_points(amp);
  TORCH_CHECK(entries.scalar_type() == at::kLong && seg.scalar_type() == at::kLong,
              "nsplat: entries and seg must be int64");
  TORCH_CHECK(seg.numel() == amp.size(1) + 1, "nsplat: seg must have N + 1 entries");
  return composite_backward_points_cuda(mu, con, amp, nrm, off, zc, Ks, entries, seg, dalpha, wf, g_img, g_depth,
                                        width, height, estimator, per_camera_features);
}

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                        at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                        bool backface_cull) {
  check_cuda({means, normals, scales, opac, viewmats, Ks});
  check_dtype({means, normals, scales, opac, viewmats, Ks});
  return project_forward_cuda(means, normals, scales, opac, viewmats, Ks, near, far, lowpass, backface_cull);
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                         at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                         bool backface_cull, at::Tensor g_means2d, at::Tensor g_conics,
                                         at::Tensor g_amps, at::Tensor g_normals_cam, at::Tensor g_plane_offsets,
                                         at::Tensor g_depths, at::Tensor g_sigma2) {
  const std::vector<at::Tensor> g = {g_means2d, g_conics, g_amps, g_normals_cam, g_plane_offsets, g_depths, g_sigma2};
  std::vector<at::Tensor> all = {means, normals, scales, opac, viewmats, Ks};
  all.insert(all.end(), g.begin(), g.end());
  check_cuda(all);
  check_dtype(all);
  return project_backward_cuda(means, normals, scales, opac, viewmats, Ks, near, far, lowpass, backface_cull, g);
}

at::Tensor view_colour_forward(at::Tensor feat, at::Tensor means, at::Tensor viewmat, int64_t degree) {
  check_cuda({feat, means, viewmat});
  check_dtype({feat, means, viewmat});
  TORCH_CHECK(degree >= 1 && degree <= 3, "nsplat view colour (CUDA): degree 1..3");
  return view_colour_forward_cuda(feat, means, viewmat, degree);
}

std::vector<at::Tensor> view_colour_backward(at::Tensor feat, at::Tensor means, at::Tensor viewmat, int64_t degree,
                                             at::Tensor g_out) {
  check_cuda({feat, means, viewmat, g_out});
  check_dtype({feat, means, viewmat, g_out});
  TORCH_CHECK(degree >= 1 && degree <= 3, "nsplat view colour (CUDA): degree 1..3");
  return view_colour_backward_cuda(feat, means, viewmat, degree, g_out);
}

}  // namespace nsplat

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("sample", &nsplat::sample, "Per-pixel SPS sample over the radix tree (CUDA)");
#if defined(NSPLAT_CUDA_EMULATE)
  m.def("merge_lanes", &nsplat::merge_lanes_emulated, "Test entry: the sampler's merge of sorted lane heaps (emulation)");
  m.def("launches", &nsplat::launches_emulated, "Test entry: kernel launches and cub primitives so far (emulation)");
#endif
  m.def("host_reads", &nsplat::host_reads_cuda, "Reads of device values by the host so far (each a synchronisation)");
  m.def("composite_forward", &nsplat::composite_forward, "Composite a given sample (CUDA)");
  m.def("composite_backward_pixels", &nsplat::composite_backward_pixels, "Backward pass 1, per pixel (CUDA)");
  m.def("composite_backward_points", &nsplat::composite_backward_points, "Backward pass 2, per point (CUDA)");
  m.def("project_forward", &nsplat::project_forward, "EWA projection of oriented surfels (CUDA)");
  m.def("project_backward", &nsplat::project_backward, "Backward of project_forward (CUDA)");
  m.def("view_colour_forward", &nsplat::view_colour_forward, "View-dependent SH colour (CUDA)");
  m.def("view_colour_backward", &nsplat::view_colour_backward, "Backward of view_colour_forward (CUDA)");
}
