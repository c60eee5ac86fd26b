// The EWA projection of oriented surfels on the CPU: the loops around core/projection.h (the model of
// ops/projection.py, whose pure-PyTorch `project_torch` is the reference, tests/test_op_projection.py). One task
// per point: the point's frame once, then every camera in order, so the per-point gradients are summed over
// cameras in a fixed order; the per-camera gradients (viewmats, Ks) are summed in double over fixed blocks of
// kProjectBlock points, then over the blocks in order. Both are bitwise identical for any thread count.
#include "projection_cpu.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace nsplat {
namespace {

int threads() { return std::max(1, at::get_num_threads()); }

// The inputs of a call: the surfels' arrays and the cameras.
template <typename S>
struct Scene {
  int64_t B, N;
  const S *M, *Nr, *Sc, *O;  // means, normals, scales, opacities
  std::vector<Camera<S>> cams;
};

template <typename S>
Scene<S> scene(const at::Tensor& means, const at::Tensor& normals, const at::Tensor& scales, const at::Tensor& opac,
               const at::Tensor& viewmats, const at::Tensor& Ks) {
  Scene<S> in{viewmats.size(0), means.size(0), means.data_ptr<S>(), normals.data_ptr<S>(), scales.data_ptr<S>(),
              opac.data_ptr<S>(), {}};
  for (int64_t b = 0; b < in.B; ++b)
    in.cams.push_back(load_camera(viewmats.data_ptr<S>() + 16 * b, Ks.data_ptr<S>() + 9 * b));
  return in;
}

template <typename S>
void forward_impl(const at::Tensor& means, const at::Tensor& normals, const at::Tensor& scales,
                  const at::Tensor& opac, const at::Tensor& viewmats, const at::Tensor& Ks, const ProjectSettings& st,
                  std::vector<at::Tensor>& out) {
  const Scene<S> in = scene<S>(means, normals, scales, opac, viewmats, Ks);
  const ProjectOutputs<S> o{out[0].data_ptr<S>(), out[1].data_ptr<S>(), out[2].data_ptr<S>(), out[3].data_ptr<S>(),
                            out[4].data_ptr<S>(), out[5].data_ptr<S>(), out[6].data_ptr<S>(),
                            out[7].data_ptr<bool>(), out[8].data_ptr<int8_t>()};
#pragma omp parallel for num_threads(threads()) schedule(static)
  for (int64_t k = 0; k < in.N; ++k) {
    const Frame<S> f = point_frame(in.Nr + 3 * k, in.Sc + 2 * k);
    for (int64_t b = 0; b < in.B; ++b) write_pair(pair(in.cams[b], f, in.M + 3 * k, st), in.O[k], b * in.N + k, o);
  }
}

template <typename S>
void backward_impl(const at::Tensor& means, const at::Tensor& normals, const at::Tensor& scales,
                   const at::Tensor& opac, const at::Tensor& viewmats, const at::Tensor& Ks, const ProjectSettings& st,
                   const std::vector<at::Tensor>& g, std::vector<at::Tensor>& out) {
  const Scene<S> in = scene<S>(means, normals, scales, opac, viewmats, Ks);
  const int64_t B = in.B, N = in.N;
  const ProjectGrads<S> grads{g[0].data_ptr<S>(), g[1].data_ptr<S>(), g[2].data_ptr<S>(), g[3].data_ptr<S>(),
                              g[4].data_ptr<S>(), g[5].data_ptr<S>(), g[6].data_ptr<S>()};
  S* dM = out[0].data_ptr<S>();
  S* dN = out[1].data_ptr<S>();
  S* dS = out[2].data_ptr<S>();
  S* dO = out[3].data_ptr<S>();
  const int64_t blocks = (N + kProjectBlock - 1) / kProjectBlock;
  std::vector<double> cam_part(static_cast<size_t>(std::max<int64_t>(blocks, 1)) * B * kCamGrads, 0.0);
#pragma omp parallel for num_threads(threads()) schedule(static)
  for (int64_t blk = 0; blk < blocks; ++blk) {
    double* part = cam_part.data() + blk * B * kCamGrads;
    for (int64_t k = blk * kProjectBlock; k < std::min(N, (blk + 1) * kProjectBlock); ++k) {
      const Frame<S> f = point_frame(in.Nr + 3 * k, in.Sc + 2 * k);
      const S* mean = in.M + 3 * k;
      PointGrad<S> acc;
      for (int64_t b = 0; b < B; ++b) {
        S cam[kCamGrads];
        pair_backward(in.cams[b], f, mean, in.O[k], pair(in.cams[b], f, mean, st), grads, b * N + k, acc, cam);
        for (int j = 0; j < kCamGrads; ++j) part[b * kCamGrads + j] += static_cast<double>(cam[j]);
      }
      finish_point(f, acc, k, dM, dN, dS, dO);
    }
  }
  S* dV = out[4].data_ptr<S>();
  S* dK = out[5].data_ptr<S>();
  for (int64_t b = 0; b < B; ++b) {
    double sum[kCamGrads] = {0};
    for (int64_t blk = 0; blk < blocks; ++blk)
      for (int j = 0; j < kCamGrads; ++j) sum[j] += cam_part[(blk * B + b) * kCamGrads + j];
    write_camera_grads(sum, dV + 16 * b, dK + 9 * b);
  }
}

void check_inputs(const std::vector<at::Tensor>& ts) {
  for (const auto& t : ts) {
    TORCH_CHECK(t.device().is_cpu(), "nsplat projection (CPU): expected CPU tensors");
    TORCH_CHECK(t.is_contiguous(), "nsplat projection (CPU): expected contiguous tensors");
    TORCH_CHECK(t.scalar_type() == ts[0].scalar_type(), "nsplat projection (CPU): expected one float dtype");
  }
}

}  // namespace

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                        at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                        bool backface_cull) {
  check_inputs({means, normals, scales, opac, viewmats, Ks});
  const int64_t B = viewmats.size(0), N = means.size(0);
  const auto o = means.options();
  std::vector<at::Tensor> out = {at::empty({B, N, 2}, o), at::empty({B, N, 3}, o), at::empty({B, N}, o),
                                 at::empty({B, N, 3}, o), at::empty({B, N}, o),    at::empty({B, N}, o),
                                 at::empty({B, N}, o),    at::empty({B, N}, o.dtype(at::kBool)),
                                 at::empty({B, N}, o.dtype(at::kChar))};
  const ProjectSettings st{near, far, lowpass, backface_cull};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_project_forward", [&] {
    forward_impl<scalar_t>(means, normals, scales, opac, viewmats, Ks, st, out);
  });
  return out;
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                         at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                         bool backface_cull, at::Tensor g_means2d, at::Tensor g_conics,
                                         at::Tensor g_amps, at::Tensor g_normals_cam, at::Tensor g_plane_offsets,
                                         at::Tensor g_depths, at::Tensor g_sigma2) {
  const std::vector<at::Tensor> g = {g_means2d, g_conics, g_amps, g_normals_cam, g_plane_offsets, g_depths, g_sigma2};
  std::vector<at::Tensor> all = {means, normals, scales, opac, viewmats, Ks};
  all.insert(all.end(), g.begin(), g.end());
  check_inputs(all);
  std::vector<at::Tensor> out = {at::empty_like(means), at::empty_like(normals), at::empty_like(scales),
                                 at::empty_like(opac),  at::empty_like(viewmats), at::empty_like(Ks)};
  const ProjectSettings st{near, far, lowpass, backface_cull};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_project_backward", [&] {
    backward_impl<scalar_t>(means, normals, scales, opac, viewmats, Ks, st, g, out);
  });
  return out;
}

}  // namespace nsplat
