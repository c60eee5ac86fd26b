// CUDA backend of the per-point stages before the sampler: the EWA projection (core/projection.h) and the
// view-dependent SH colour (core/view_colour.h), forward and hand-derived backward, so that a training step runs
// them as a few kernels instead of hundreds of element-wise PyTorch ones. The same functions as the CPU backend
// (cpu/projection_cpu.cpp, cpu/view_colour_cpu.cpp), in these launches:
//   project_forward_cuda       one thread per (camera, point)
//   project_backward_cuda      one thread per point over its cameras in order (the point's gradients), then one
//                              thread per (block of kProjectBlock points, camera) summing the camera's gradients
//                              over the block's points in order (in double), then one thread per camera summing
//                              the blocks in order: the CPU's summation order, so deterministic run to run
//   view_colour_forward_cuda   one thread per point
//   view_colour_backward_cuda  one thread per point, then one per block of kColourBlock points summing the
//                              means' gradients in order, then one thread folding the blocks in order
// No atomics; the camera-gradient pass recomputes each pair rather than storing B x N x 18 contributions.
// With NSPLAT_CUDA_EMULATE (emulate.cpp) this file compiles with the host compiler and runs on the CPU.
#include "launch.h"

#include "../core/projection.h"
#include "../core/view_colour.h"

namespace nsplat {
namespace {

// Per-point inputs of the projection ([N,3], [N,3], [N,2], [N]) and the cameras ([B,4,4], [B,3,3]).
template <typename S>
struct ProjectInputs {
  const S *means, *normals, *scales, *opac, *viewmats, *Ks;
  int64_t B, N;
};

template <typename S>
__global__ void project_forward_kernel(ProjectInputs<S> in, ProjectSettings st, ProjectOutputs<S> out) {
  NS_GRID_STRIDE(o, in.B * in.N) {
    const int64_t b = o / in.N, k = o - b * in.N;
    const Frame<S> f = point_frame(in.normals + 3 * k, in.scales + 2 * k);
    const Camera<S> c = load_camera(in.viewmats + 16 * b, in.Ks + 9 * b);
    write_pair(pair(c, f, in.means + 3 * k, st), in.opac[k], o, out);
  }
}

template <typename S>
__global__ void project_backward_points_kernel(ProjectInputs<S> in, ProjectSettings st, ProjectGrads<S> g, S* dM,
                                               S* dN, S* dS, S* dO) {
  NS_GRID_STRIDE(k, in.N) {
    const Frame<S> f = point_frame(in.normals + 3 * k, in.scales + 2 * k);
    const S* mean = in.means + 3 * k;
    PointGrad<S> acc;
    for (int64_t b = 0; b < in.B; ++b) {
      const Camera<S> c = load_camera(in.viewmats + 16 * b, in.Ks + 9 * b);
      S cam[kCamGrads];
      pair_backward(c, f, mean, in.opac[k], pair(c, f, mean, st), g, b * in.N + k, acc, cam);
    }
    finish_point(f, acc, k, dM, dN, dS, dO);
  }
}

// part [blocks, B, kCamGrads]: camera b's gradients summed over block blk's points in order.
template <typename S>
__global__ void project_backward_cameras_kernel(ProjectInputs<S> in, ProjectSettings st, ProjectGrads<S> g,
                                                int64_t blocks, double* part) {
  NS_GRID_STRIDE(i, blocks * in.B) {
    const int64_t blk = i / in.B, b = i - blk * in.B;
    const Camera<S> c = load_camera(in.viewmats + 16 * b, in.Ks + 9 * b);
    double sum[kCamGrads] = {0};
    const int64_t end = (blk + 1) * kProjectBlock < in.N ? (blk + 1) * kProjectBlock : in.N;
    for (int64_t k = blk * kProjectBlock; k < end; ++k) {
      const Frame<S> f = point_frame(in.normals + 3 * k, in.scales + 2 * k);
      const S* mean = in.means + 3 * k;
      PointGrad<S> unused;
      S cam[kCamGrads];
      pair_backward(c, f, mean, in.opac[k], pair(c, f, mean, st), g, b * in.N + k, unused, cam);
      for (int j = 0; j < kCamGrads; ++j) sum[j] += static_cast<double>(cam[j]);
    }
    for (int j = 0; j < kCamGrads; ++j) part[i * kCamGrads + j] = sum[j];
  }
}

template <typename S>
__global__ void project_backward_fold_kernel(int64_t B, int64_t blocks, const double* part, S* dV, S* dK) {
  NS_GRID_STRIDE(b, B) {
    double sum[kCamGrads] = {0};
    for (int64_t blk = 0; blk < blocks; ++blk)
      for (int j = 0; j < kCamGrads; ++j) sum[j] += part[(blk * B + b) * kCamGrads + j];
    write_camera_grads(sum, dV + 16 * b, dK + 9 * b);
  }
}

template <typename S>
__global__ void view_colour_forward_kernel(const S* feat, const S* means, const S* viewmat, int64_t N, int64_t F,
                                           int degree, S* out) {
  NS_GRID_STRIDE(k, N) {
    S c[3];
    centre(viewmat, c);
    colour_point(feat + k * F, means + 3 * k, c, degree, out + 3 * k);
  }
}

template <typename S>
__global__ void view_colour_backward_kernel(const S* feat, const S* means, const S* viewmat, int64_t N, int64_t F,
                                            int degree, const S* g, S* gf, S* gm) {
  NS_GRID_STRIDE(k, N) {
    S c[3];
    centre(viewmat, c);
    colour_point_backward(feat + k * F, means + 3 * k, c, degree, F, g + 3 * k, gf + k * F, gm + 3 * k);
  }
}

// part [blocks, 3]: the means' gradients (gm [N,3]) summed over block blk of kColourBlock points in order.
template <typename S>
__global__ void view_colour_parts_kernel(const S* gm, int64_t N, int64_t blocks, double* part) {
  NS_GRID_STRIDE(blk, blocks) {
    double pc[3] = {0, 0, 0};
    const int64_t end = (blk + 1) * kColourBlock < N ? (blk + 1) * kColourBlock : N;
    for (int64_t k = blk * kColourBlock; k < end; ++k)
      for (int i = 0; i < 3; ++i) pc[i] += static_cast<double>(gm[3 * k + i]);
    for (int i = 0; i < 3; ++i) part[3 * blk + i] = pc[i];
  }
}

// The viewmat's gradient from the blocks' sums, folded in order by one thread.
template <typename S>
__global__ void view_colour_viewmat_kernel(const double* part, int64_t blocks, const S* viewmat, S* gv) {
  NS_GRID_STRIDE(t, 1) {
    double gc[3] = {0, 0, 0};
    for (int64_t blk = 0; blk < blocks; ++blk)
      for (int i = 0; i < 3; ++i) gc[i] -= part[3 * blk + i];
    write_viewmat_grad(viewmat, gc, gv);
  }
}

template <typename S>
ProjectInputs<S> project_inputs(const at::Tensor& means, const at::Tensor& normals, const at::Tensor& scales,
                                const at::Tensor& opac, const at::Tensor& viewmats, const at::Tensor& Ks) {
  return {means.data_ptr<S>(), normals.data_ptr<S>(), scales.data_ptr<S>(), opac.data_ptr<S>(),
          viewmats.data_ptr<S>(), Ks.data_ptr<S>(), viewmats.size(0), means.size(0)};
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Entry points (argument checks in bindings.cpp); signatures and outputs as cpu/projection_cpu.h and
// cpu/view_colour_cpu.h.

std::vector<at::Tensor> project_forward_cuda(const at::Tensor& means, const at::Tensor& normals,
                                             const at::Tensor& scales, const at::Tensor& opac,
                                             const at::Tensor& viewmats, const at::Tensor& Ks, double near, double far,
                                             double lowpass, bool backface_cull) {
  const DeviceGuard guard(means.device());
  const Stream stream = current_stream();
  const int64_t B = viewmats.size(0), N = means.size(0);
  const auto o = means.options();
  std::vector<at::Tensor> out = {at::empty({B, N, 2}, o), at::empty({B, N, 3}, o), at::empty({B, N}, o),
                                 at::empty({B, N, 3}, o), at::empty({B, N}, o),    at::empty({B, N}, o),
                                 at::empty({B, N}, o),    at::empty({B, N}, o.dtype(at::kBool)),
                                 at::empty({B, N}, o.dtype(at::kChar))};
  if (B * N == 0) return out;
  const ProjectSettings st{near, far, lowpass, backface_cull};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_project_forward_cuda", [&] {
    using S = scalar_t;
    const ProjectOutputs<S> po{out[0].data_ptr<S>(), out[1].data_ptr<S>(), out[2].data_ptr<S>(),
                               out[3].data_ptr<S>(), out[4].data_ptr<S>(), out[5].data_ptr<S>(),
                               out[6].data_ptr<S>(), out[7].data_ptr<bool>(), out[8].data_ptr<int8_t>()};
    NS_LAUNCH(project_forward_kernel<S>, blocks_for(B * N, kThreads), kThreads, stream,
              project_inputs<S>(means, normals, scales, opac, viewmats, Ks), st, po);
    NS_LAUNCH_CHECK();
  });
  return out;
}

std::vector<at::Tensor> project_backward_cuda(const at::Tensor& means, const at::Tensor& normals,
                                              const at::Tensor& scales, const at::Tensor& opac,
                                              const at::Tensor& viewmats, const at::Tensor& Ks, double near,
                                              double far, double lowpass, bool backface_cull,
                                              const std::vector<at::Tensor>& g) {
  const DeviceGuard guard(means.device());
  const Stream stream = current_stream();
  const int64_t B = viewmats.size(0), N = means.size(0);
  std::vector<at::Tensor> out = {at::zeros_like(means), at::zeros_like(normals), at::zeros_like(scales),
                                 at::zeros_like(opac),  at::zeros_like(viewmats), at::zeros_like(Ks)};
  if (B * N == 0) return out;
  const ProjectSettings st{near, far, lowpass, backface_cull};
  const int64_t blocks = (N + kProjectBlock - 1) / kProjectBlock;
  at::Tensor part = at::empty({blocks * B * kCamGrads}, means.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_project_backward_cuda", [&] {
    using S = scalar_t;
    const ProjectInputs<S> in = project_inputs<S>(means, normals, scales, opac, viewmats, Ks);
    const ProjectGrads<S> pg{g[0].data_ptr<S>(), g[1].data_ptr<S>(), g[2].data_ptr<S>(), g[3].data_ptr<S>(),
                             g[4].data_ptr<S>(), g[5].data_ptr<S>(), g[6].data_ptr<S>()};
    NS_LAUNCH(project_backward_points_kernel<S>, blocks_for(N, kThreads), kThreads, stream, in, st, pg,
              out[0].data_ptr<S>(), out[1].data_ptr<S>(), out[2].data_ptr<S>(), out[3].data_ptr<S>());
    NS_LAUNCH_CHECK();
    NS_LAUNCH(project_backward_cameras_kernel<S>, blocks_for(blocks * B, 64), 64, stream, in, st, pg, blocks,
              part.data_ptr<double>());
    NS_LAUNCH_CHECK();
    NS_LAUNCH(project_backward_fold_kernel<S>, blocks_for(B, 64), 64, stream, B, blocks, part.data_ptr<double>(),
              out[4].data_ptr<S>(), out[5].data_ptr<S>());
    NS_LAUNCH_CHECK();
  });
  return out;
}

at::Tensor view_colour_forward_cuda(const at::Tensor& feat, const at::Tensor& means, const at::Tensor& viewmat,
                                    int64_t degree) {
  const DeviceGuard guard(means.device());
  const Stream stream = current_stream();
  const int64_t N = means.size(0), F = feat.size(1);
  at::Tensor out = at::empty({N, 3}, means.options());
  if (N == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_view_colour_forward_cuda", [&] {
    using S = scalar_t;
    NS_LAUNCH(view_colour_forward_kernel<S>, blocks_for(N, kThreads), kThreads, stream, feat.data_ptr<S>(),
              means.data_ptr<S>(), viewmat.data_ptr<S>(), N, F, static_cast<int>(degree), out.data_ptr<S>());
    NS_LAUNCH_CHECK();
  });
  return out;
}

std::vector<at::Tensor> view_colour_backward_cuda(const at::Tensor& feat, const at::Tensor& means,
                                                  const at::Tensor& viewmat, int64_t degree, const at::Tensor& g_out) {
  const DeviceGuard guard(means.device());
  const Stream stream = current_stream();
  const int64_t N = means.size(0), F = feat.size(1);
  at::Tensor g_feat = at::zeros_like(feat), g_means = at::zeros_like(means), g_view = at::zeros_like(viewmat);
  const int64_t blocks = (N + kColourBlock - 1) / kColourBlock;
  at::Tensor part = at::zeros({std::max<int64_t>(blocks, 1) * 3}, means.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_view_colour_backward_cuda", [&] {
    using S = scalar_t;
    if (N > 0) {
      NS_LAUNCH(view_colour_backward_kernel<S>, blocks_for(N, kThreads), kThreads, stream, feat.data_ptr<S>(),
                means.data_ptr<S>(), viewmat.data_ptr<S>(), N, F, static_cast<int>(degree), g_out.data_ptr<S>(),
                g_feat.data_ptr<S>(), g_means.data_ptr<S>());
      NS_LAUNCH_CHECK();
    }
    NS_LAUNCH(view_colour_parts_kernel<S>, blocks_for(blocks, 64), 64, stream, g_means.data_ptr<S>(), N, blocks,
              part.data_ptr<double>());
    NS_LAUNCH_CHECK();
    NS_LAUNCH(view_colour_viewmat_kernel<S>, 1, 1, stream, part.data_ptr<double>(), blocks, viewmat.data_ptr<S>(),
              g_view.data_ptr<S>());
    NS_LAUNCH_CHECK();
  });
  return {g_feat, g_means, g_view};
}

}  // namespace nsplat
