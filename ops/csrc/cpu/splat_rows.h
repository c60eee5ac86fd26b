// What the CPU compositor's passes share: camera b's rows of the projected splats, the thread count, and the
// per-(camera, point) geometry gradient with the output rows it goes to (splat_cpu.cpp, scatter_cpu.cpp).
#pragma once
#include <torch/extension.h>

#include <algorithm>
#include <vector>

#include "../core/composite.h"

namespace nsplat {

// OpenMP threads of a native call: PyTorch's intra-op thread count.
inline int num_threads() { return std::max(1, at::get_num_threads()); }

// Camera b's splats: rows b of mu [B,N,2], con [B,N,3], amp [B,N], nrm [B,N,3], off [B,N], zc [B,N].
template <typename S>
SplatsView<S> splats_of(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& nrm,
                        const at::Tensor& off, const at::Tensor& zc, int64_t b) {
  const int64_t N = amp.size(1);
  SplatsView<S> v;
  v.mu = mu.data_ptr<S>() + b * N * 2;
  v.con = con.data_ptr<S>() + b * N * 3;
  v.amp = amp.data_ptr<S>() + b * N;
  v.nrm = nrm.data_ptr<S>() + b * N * 3;
  v.off = off.data_ptr<S>() + b * N;
  v.zc = zc.data_ptr<S>() + b * N;
  return v;
}

// One (camera, point) gradient w.r.t. the projected parameters, summed over that point's slots.
template <typename S>
struct SplatGrad {
  S mu[2] = {0, 0}, con[3] = {0, 0, 0}, amp = 0, nrm[3] = {0, 0, 0}, off = 0, zc = 0;

  // Adds the slot of point k at pixel (u, v) (splat_grad_entry).
  void add(const SplatsView<S>& sv, int k, S u, S v, const Ray& ray, S dla, S dld) {
    splat_grad_entry(sv, k, u, v, ray, dla, dld, mu, con, &amp, nrm, &off, &zc);
  }
};

// The backward's outputs {g_mu [B,N,2], g_con [B,N,3], g_amp [B,N], g_nrm [B,N,3], g_off [B,N], g_zc [B,N],
// g_feat} as pointers; put(bk, g, scale, op) applies op(destination, value) to row bk = b·N + k.
template <typename S>
struct GradRows {
  S *mu, *con, *amp, *nrm, *off, *zc, *feat;

  explicit GradRows(std::vector<at::Tensor>& out)
      : mu(out[0].data_ptr<S>()), con(out[1].data_ptr<S>()), amp(out[2].data_ptr<S>()), nrm(out[3].data_ptr<S>()),
        off(out[4].data_ptr<S>()), zc(out[5].data_ptr<S>()), feat(out[6].data_ptr<S>()) {}

  template <typename Op>
  void put(int64_t bk, const SplatGrad<S>& g, S scale, Op op) const {
    for (int c = 0; c < 2; ++c) op(mu + bk * 2 + c, g.mu[c] * scale);
    for (int c = 0; c < 3; ++c) op(con + bk * 3 + c, g.con[c] * scale);
    for (int c = 0; c < 3; ++c) op(nrm + bk * 3 + c, g.nrm[c] * scale);
    op(amp + bk, g.amp * scale);
    op(off + bk, g.off * scale);
    op(zc + bk, g.zc * scale);
  }
};

}  // namespace nsplat
