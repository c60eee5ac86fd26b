// Non-deterministic, single-pass CPU backward of the compositor (``splat(..., deterministic=False)``).
//
// The deterministic backward (splat_cpu.cpp) runs pass 1 per pixel into [B,H,W,m] buffers, sorts all
// filled slots by (point, camera, slot) and gathers them per point in that fixed order. Here each
// thread takes a pixel, runs pass 1 into thread-local slot arrays and immediately chains every slot
// through splat_grad_entry, adding the result to the per-point gradient buffers with OpenMP atomics.
// The "paper" estimator's 1/|N_k| (pixels of camera b where k was sampled) is applied per entry from a
// count computed in a first, cheap pass over the indices. Floating-point addition order depends on
// the thread schedule, so gradients match the deterministic path only up to rounding.
#include "scatter_cpu.h"

#include <algorithm>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

#include "../api.h"  // camera_features
#include "../core/composite.h"
#include "splat_rows.h"

namespace nsplat {
namespace {

template <typename S>
inline void atomic_add(S* dst, S v) {
  if (v != S(0)) {
#pragma omp atomic
    *dst += v;
  }
}

template <typename S>
void scatter_impl(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& nrm,
                  const at::Tensor& off, const at::Tensor& zc, const at::Tensor& Kd, const at::Tensor& feat,
                  const at::Tensor& bg, const at::Tensor& indices, const at::Tensor& probs, int mode, int estimator,
                  const at::Tensor& g_img, const at::Tensor& g_alpha, const at::Tensor& g_depth,
                  std::vector<at::Tensor>& out) {
  const int64_t B = indices.size(0), H = indices.size(1), W = indices.size(2), m = indices.size(3);
  const int64_t N = amp.size(1), C = feat.size(-1), P = H * W;
  const bool per_camera = feat.dim() == 3;  // [B,N,C]: camera b's own features, and gradients
  const int nt = num_threads();
  const int* idx_all = indices.data_ptr<int>();
  const bool paper = estimator == kPaper;
  std::vector<int> count;
  if (paper) {
    count.assign(static_cast<size_t>(B * N), 0);
    int* cnt = count.data();
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t o = 0; o < B * P; ++o) {
      const int64_t b = o / P;
      for (int64_t j = 0; j < m; ++j) {
        const int k = idx_all[o * m + j];
        if (k < 0) break;
#pragma omp atomic
        cnt[b * N + k] += 1;
      }
    }
  }
  const S* gi = g_img.data_ptr<S>();
  const S* ga = g_alpha.data_ptr<S>();
  const S* gd = g_depth.data_ptr<S>();
  const S* bgp = bg.data_ptr<S>();
  const S* pr = probs.data_ptr<S>();
  const GradRows<S> rows(out);
  S* o_bgw = out[7].data_ptr<S>();
#pragma omp parallel num_threads(nt)
  {
    std::vector<S> da(m), wf(m);
    for (int64_t b = 0; b < B; ++b) {
      const SplatsView<S> sv = splats_of<S>(mu, con, amp, nrm, off, zc, b);
      const double* K = Kd.data_ptr<double>() + b * 9;
      const S* fe = camera_features<S>(feat, b);
#pragma omp for schedule(static)
      for (int64_t p = 0; p < P; ++p) {
        const int64_t o = b * P + p;
        const double u = double(p % W) + 0.5, v = double(p / W) + 0.5;
        const Ray ray = pixel_ray(K, u, v);
        const int* idx = idx_all + o * m;
        o_bgw[o] = composite_backward_pixel(sv, fe, static_cast<int>(C), bgp, idx, pr + o * m, static_cast<int>(m),
                                            S(u), S(v), ray, mode, estimator, gi + o * C, ga[o], gd[o], da.data(),
                                            wf.data());
        for (int64_t j = 0; j < m; ++j) {
          const int k = idx[j];
          if (k < 0) break;
          const S scale = paper ? S(1) / S(count[b * N + k]) : S(1);
          SplatGrad<S> g;
          g.add(sv, k, S(u), S(v), ray, da[j] * scale, wf[j] * gd[o] * scale);
          const int64_t bk = b * N + k;
          rows.put(bk, g, S(1), atomic_add<S>);
          const S wfs = wf[j] * scale;
          S* of = rows.feat + (per_camera ? bk : static_cast<int64_t>(k)) * C;
          for (int64_t c = 0; c < C; ++c) atomic_add(of + c, wfs * gi[o * C + c]);
        }
      }
    }
  }
}

}  // namespace

std::vector<at::Tensor> composite_backward_scatter(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                   at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor feat,
                                                   at::Tensor bg, at::Tensor indices, at::Tensor probs, int64_t mode,
                                                   int64_t estimator, at::Tensor g_img, at::Tensor g_alpha,
                                                   at::Tensor g_depth) {
  for (const auto& t : {mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, g_img, g_alpha, g_depth}) {
    TORCH_CHECK(t.device().is_cpu(), "nsplat CPU backend got a tensor on ", t.device());
    TORCH_CHECK(t.is_contiguous(), "nsplat CPU backend expects contiguous tensors");
  }
  check_features(feat, amp);
  const int64_t B = amp.size(0), N = amp.size(1);
  const int64_t H = indices.size(1), W = indices.size(2);
  auto opts = mu.options();
  std::vector<at::Tensor> out = {at::zeros({B, N, 2}, opts), at::zeros({B, N, 3}, opts), at::zeros({B, N}, opts),
                                 at::zeros({B, N, 3}, opts), at::zeros({B, N}, opts),    at::zeros({B, N}, opts),
                                 at::zeros_like(feat),       at::empty({B, H, W, 1}, opts)};
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_composite_backward_scatter", [&] {
    scatter_impl<scalar_t>(mu, con, amp, nrm, off, zc, Kd, feat, bg, indices, probs, static_cast<int>(mode),
                           static_cast<int>(estimator), g_img, g_alpha, g_depth, out);
  });
  return out;
}

}  // namespace nsplat
