// Tiled render of every splat within a Mahalanobis radius (CPU): the dense oracle's image with each kernel cut
// where it falls below exp(-cutoff2 / 2) of its peak, at a cost of pixels x (splats that reach the pixel).
//
// Binning: splat k reaches the pixels whose centre lies in the square of half-width sqrt(cutoff2 * sigma2_k)
// about mu_k (sigma2_k the largest eigenvalue of Sigma_k, so the square holds the ellipse q <= cutoff2). Each
// square is listed in every kTiledTile x kTiledTile tile it overlaps, in point order.
// Pixel: the listed splats with q(x) <= cutoff2 are taken by (per-pixel depth, point index) -- the dense
// oracle's stable depth sort -- and composited front to back as in core/composite.h (alpha mode) until the
// transmittance falls below t_stop (the rest would move the pixel by less than t_stop times its features).
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include <omp.h>

#include "../core/ewa.h"
#include "../core/sps.h"
#include "splat_rows.h"
#include "tiled_cpu.h"

namespace nsplat {
namespace {

constexpr int64_t kTiledTile = 8;  // tile edge in pixels

// A splat in reach of a pixel: per-pixel depth, index, alpha; `before`: front to back by (depth, index).
template <typename S>
struct Reach {
  S d;
  int k;
  S a;
  static bool before(const Reach& x, const Reach& y) { return x.d < y.d || (x.d == y.d && x.k < y.k); }
};

template <typename S>
void tiled_impl(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& sig2,
                const at::Tensor& nrm, const at::Tensor& off, const at::Tensor& zc, const at::Tensor& Kd,
                const at::Tensor& feat, const at::Tensor& bg, double cutoff2, double t_stop, at::Tensor& image,
                at::Tensor& alpha, at::Tensor& depth, at::Tensor& weights) {
  const int64_t B = amp.size(0), N = amp.size(1), H = image.size(1), W = image.size(2), C = feat.size(-1);
  const int64_t tx = (W + kTiledTile - 1) / kTiledTile, ty = (H + kTiledTile - 1) / kTiledTile;
  const int nt = num_threads();
  std::vector<int64_t> start(tx * ty + 1);
  std::vector<int> items;
  for (int64_t b = 0; b < B; ++b) {
    const SplatsView<S> sv = splats_of<S>(mu, con, amp, nrm, off, zc, b);
    const S* s2 = sig2.data_ptr<S>() + b * N;
    const double* K = Kd.data_ptr<double>() + b * 9;
    const S* fb = feat.data_ptr<S>() + (feat.dim() == 3 ? b * N * C : 0);
    // tile range [x0, x1] x [y0, y1] of each splat's square (x1 < x0: reaches no pixel centre)
    std::vector<int64_t> box(4 * N);
    for (int64_t k = 0; k < N; ++k) {
      int64_t* r = box.data() + 4 * k;
      const double amp_k = static_cast<double>(sv.amp[k]);
      const double half = std::sqrt(cutoff2 * static_cast<double>(s2[k]));
      const double ux = static_cast<double>(sv.mu[2 * k]), uy = static_cast<double>(sv.mu[2 * k + 1]);
      if (!(amp_k > 0.0) || !std::isfinite(half) || !std::isfinite(ux) || !std::isfinite(uy)) {
        r[0] = 1; r[1] = 0; r[2] = 1; r[3] = 0;
        continue;
      }
      // pixel columns i with |i + 0.5 - ux| <= h, clipped to the image, then their tiles
      const double lo_x = std::max(0.0, std::ceil(ux - half - 0.5));
      const double hi_x = std::min(double(W - 1), std::floor(ux + half - 0.5));
      const double lo_y = std::max(0.0, std::ceil(uy - half - 0.5));
      const double hi_y = std::min(double(H - 1), std::floor(uy + half - 0.5));
      if (lo_x > hi_x || lo_y > hi_y) {
        r[0] = 1; r[1] = 0; r[2] = 1; r[3] = 0;
        continue;
      }
      r[0] = static_cast<int64_t>(lo_x) / kTiledTile; r[1] = static_cast<int64_t>(hi_x) / kTiledTile;
      r[2] = static_cast<int64_t>(lo_y) / kTiledTile; r[3] = static_cast<int64_t>(hi_y) / kTiledTile;
    }
    std::fill(start.begin(), start.end(), 0);
    for (int64_t k = 0; k < N; ++k) {
      const int64_t* r = box.data() + 4 * k;
      for (int64_t y = r[2]; y <= r[3]; ++y)
        for (int64_t x = r[0]; x <= r[1]; ++x) ++start[y * tx + x + 1];
    }
    for (int64_t t = 0; t < tx * ty; ++t) start[t + 1] += start[t];
    items.resize(start[tx * ty]);
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (int64_t k = 0; k < N; ++k) {  // in point order: each tile's list is sorted by index
      const int64_t* r = box.data() + 4 * k;
      for (int64_t y = r[2]; y <= r[3]; ++y)
        for (int64_t x = r[0]; x <= r[1]; ++x) items[fill[y * tx + x]++] = static_cast<int>(k);
    }
    // per-thread sums of each splat's compositing weights, added in thread order after the pass: with a static
    // schedule the sums are the same on every run with the same thread count
    const bool sum_weights = weights.numel() > 0;
    std::vector<std::vector<double>> acc(sum_weights ? nt : 0);
#pragma omp parallel num_threads(nt)
    {
      std::vector<Reach<S>> cand;
      std::vector<double>* mine = sum_weights ? &acc[omp_get_thread_num()] : nullptr;
      if (mine != nullptr) mine->assign(N, 0.0);
#pragma omp for schedule(static, 1)
      for (int64_t t = 0; t < tx * ty; ++t) {
        const int64_t x0 = (t % tx) * kTiledTile, y0 = (t / tx) * kTiledTile;
        const int* list = items.data() + start[t];
        const int64_t count = start[t + 1] - start[t];
        for (int64_t y = y0; y < std::min(H, y0 + kTiledTile); ++y) {
          for (int64_t x = x0; x < std::min(W, x0 + kTiledTile); ++x) {
            const double u = double(x) + 0.5, v = double(y) + 0.5;
            const Ray ray = pixel_ray(K, u, v);
            cand.clear();
            for (int64_t i = 0; i < count; ++i) {
              const int k = list[i];
              const S dx = S(u) - sv.mu[2 * k], dy = S(v) - sv.mu[2 * k + 1];
              const S* c = sv.con + 3 * k;
              const S q = c[0] * dx * dx + S(2) * c[1] * dx * dy + c[2] * dy * dy;
              if (!(q <= S(cutoff2))) continue;
              bool on_plane;
              S dot;
              const S d = splat_depth(sv.nrm + 3 * k, sv.off[k], sv.zc[k], ray, &on_plane, &dot);
              const S raw = sv.amp[k] * sexp(S(-0.5) * q);
              cand.push_back({d, k, raw > S(kAlphaMax) ? S(kAlphaMax) : raw});
            }
            std::sort(cand.begin(), cand.end(), Reach<S>::before);  // the oracle's stable depth sort
            const int64_t o = (b * H + y) * W + x;
            S* img = image.data_ptr<S>() + o * C;
            for (int64_t ch = 0; ch < C; ++ch) img[ch] = S(0);
            S T = S(1), dep = S(0);
            for (size_t j = 0; j < cand.size() && T >= S(t_stop); ++j) {
              const Reach<S>& r = cand[j];
              const S w = r.a * T;
              if (mine != nullptr) (*mine)[r.k] += static_cast<double>(w);
              const S* f = fb + static_cast<int64_t>(r.k) * C;
              for (int64_t ch = 0; ch < C; ++ch) img[ch] += w * f[ch];
              dep += w * r.d;
              T *= S(1) - r.a;
            }
            const S* bgp = bg.data_ptr<S>();
            for (int64_t ch = 0; ch < C; ++ch) img[ch] += T * bgp[ch];
            alpha.data_ptr<S>()[o] = S(1) - T;
            depth.data_ptr<S>()[o] = dep;
          }
        }
      }
    }
    if (sum_weights) {
      S* wb = weights.data_ptr<S>() + b * N;
      for (int64_t k = 0; k < N; ++k) {
        double total = 0.0;
        for (const auto& part : acc) total += part.empty() ? 0.0 : part[k];
        wb[k] = static_cast<S>(total);
      }
    }
  }
}

}  // namespace

std::vector<at::Tensor> render_tiled(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                                     at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor feat, at::Tensor bg,
                                     int64_t width, int64_t height, double cutoff2, double t_stop,
                                     bool point_weights) {
  for (const auto& t : {mu, con, amp, sig2, nrm, off, zc, Ks, feat, bg}) {
    TORCH_CHECK(t.device().is_cpu() && t.is_contiguous(), "nsplat render_tiled expects contiguous CPU tensors");
  }
  check_features(feat, amp);
  TORCH_CHECK(cutoff2 > 0.0, "nsplat render_tiled: cutoff2 must be > 0");
  const int64_t B = amp.size(0), C = feat.size(-1);
  auto opts = mu.options();
  at::Tensor image = at::empty({B, height, width, C}, opts);
  at::Tensor alpha = at::empty({B, height, width, 1}, opts);
  at::Tensor depth = at::empty({B, height, width, 1}, opts);
  at::Tensor weights = at::zeros({point_weights ? B : 0, amp.size(1)}, opts);
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_render_tiled", [&] {
    tiled_impl<scalar_t>(mu, con, amp, sig2, nrm, off, zc, Kd, feat, bg, cutoff2, t_stop, image, alpha, depth, weights);
  });
  return {image, alpha, depth, weights};
}

}  // namespace nsplat
