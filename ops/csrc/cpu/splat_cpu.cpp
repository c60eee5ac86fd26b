// CPU backend: OpenMP loops over cameras' points, tree nodes and pixels calling the shared core.
#include <torch/extension.h>

#include <algorithm>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

#include "../api.h"  // the declarations this file defines; bound in bindings.cpp
#include "../core/composite.h"
#include "../core/sps.h"
#include "../core/tile.h"
#include "../core/tree_build.h"
#include "lanes_api.h"
#include "splat_rows.h"

namespace nsplat {
namespace {

// A camera's tree with its storage. The storage is kept from one tree to the next (a thread's trees reuse it:
// sample_impl), so that a step's tree costs its writes, not fresh pages and their zero fill.
struct CpuTree {
  std::vector<InternalNode> nodes;
  std::vector<NodeAgg> agg;
  std::vector<int> herm_p, parent_int, parent_leaf, flags, id;
  std::vector<int64_t> herm_off;
  std::vector<double> herm_err, mu, con, logA, amp, sig2, nrm, off, zc;
  std::unique_ptr<double[]> herm_coef;                // filled on first use (lazy_hermite.h)
  std::unique_ptr<std::atomic<uint8_t>[]> herm_state;  // zero: none computed
  std::vector<ItemMetric> metric;                     // of the nodes that tile_items can cut into groups
  std::vector<int64_t> valid;                         // build scratch: indices of the valid points,
  std::vector<uint64_t> keys, sort_tmp;               // their tree keys and the radix sort's buffer
  int64_t coef_cap = 0, state_cap = 0;                // allocated sizes of herm_coef and herm_state
  int64_t n = 0;

  TreeView view() const {
    TreeView t;
    t.n = n;
    t.nodes = nodes.data();
    t.agg = agg.data();
    t.herm_p = herm_p.data();
    t.herm_off = herm_off.data();
    t.herm_err = herm_err.data();
    t.herm_coef = herm_coef.get();
    t.mu = mu.data();
    t.con = con.data();
    t.logA = logA.data();
    t.sig2 = sig2.data();
    t.id = id.data();
    return t;
  }
};

// The calling thread's tree storage (OpenMP workers reach it through the reference, not the thread_local).
CpuTree& thread_tree() {
  static thread_local CpuTree tree;
  return tree;
}

// Sorts the unique 64-bit tree keys (morton_key: code in the high word, original index in the low word; `keys` in
// increasing index order) ascending: a stable LSD radix sort of the high words (11, 11 and 10 bits), which leaves
// equal codes in index order, i.e. the order of the whole keys.
void sort_keys(std::vector<uint64_t>& keys, std::vector<uint64_t>& tmp) {
  tmp.resize(keys.size());
  const int shifts[3] = {32, 43, 54};
  for (int pass = 0; pass < 3; ++pass) {
    const int shift = shifts[pass];
    size_t count[2049] = {0};
    for (uint64_t k : keys) ++count[((k >> shift) & 2047) + 1];
    for (int b = 0; b < 2048; ++b) count[b + 1] += count[b];
    for (uint64_t k : keys) tmp[count[(k >> shift) & 2047]++] = k;
    keys.swap(tmp);
  }
}

// Builds a camera's tree over its valid points (amp > 0); the sorted copies of nrm / off / zc (per-pixel depth)
// are taken only when `nrm` is not null.
template <typename S>
void build_tree(CpuTree& T, const S* mu, const S* con, const S* amp, const S* sig2, const S* nrm, const S* off,
                const S* zc, int64_t N, int order, double tol) {
  std::vector<int64_t>& valid = T.valid;
  valid.clear();
  valid.reserve(N);
  double lox = INFINITY, loy = INFINITY, hix = -INFINITY, hiy = -INFINITY;
  for (int64_t k = 0; k < N; ++k) {
    if (!(amp[k] > S(0))) continue;
    valid.push_back(k);
    lox = std::min(lox, double(mu[2 * k]));
    hix = std::max(hix, double(mu[2 * k]));
    loy = std::min(loy, double(mu[2 * k + 1]));
    hiy = std::max(hiy, double(mu[2 * k + 1]));
  }
  const int64_t n = static_cast<int64_t>(valid.size());
  T.n = n;
  if (n == 0) return;
  double ext = std::max(hix - lox, hiy - loy);
  double inv_ext = ext > 0 ? 1.0 / ext : 0.0;
  std::vector<uint64_t>& keys = T.keys;
  keys.resize(n);
  const int nt = num_threads();
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    int64_t k = valid[i];
    keys[i] = morton_key(double(mu[2 * k]), double(mu[2 * k + 1]), double(sig2[k]), lox, loy, inv_ext, k);
  }
  sort_keys(keys, T.sort_tmp);
  T.id.resize(n);
  T.mu.resize(2 * n);
  T.con.resize(3 * n);
  T.logA.resize(n);
  T.amp.resize(n);
  T.sig2.resize(n);
  if (nrm) {
    T.nrm.resize(3 * n);
    T.off.resize(n);
    T.zc.resize(n);
  }
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t s = 0; s < n; ++s) {
    int64_t k = static_cast<int64_t>(keys[s] & 0xFFFFFFFFull);
    T.id[s] = static_cast<int>(k);
    T.mu[2 * s] = double(mu[2 * k]);
    T.mu[2 * s + 1] = double(mu[2 * k + 1]);
    for (int c = 0; c < 3; ++c) T.con[3 * s + c] = double(con[3 * k + c]);
    T.amp[s] = double(amp[k]);
    T.logA[s] = std::log(T.amp[s]);
    T.sig2[s] = double(sig2[k]);
    if (nrm) {
      for (int c = 0; c < 3; ++c) T.nrm[3 * s + c] = double(nrm[3 * k + c]);
      T.off[s] = double(off[k]);
      T.zc[s] = double(zc[k]);
    }
  }
  if (n == 1) return;
  const int64_t ni = n - 1;
  T.nodes.resize(ni);
  T.agg.resize(ni);
  T.parent_int.assign(ni, -1);
  T.parent_leaf.assign(n, -1);
  T.flags.assign(ni, 0);
  T.herm_p.assign(ni, 0);
  T.herm_err.assign(ni, 0.0);
  T.herm_off.assign(ni, 0);
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t i = 0; i < ni; ++i) build_internal_node(keys.data(), n, i, T.nodes.data(), T.parent_int.data(), T.parent_leaf.data());
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t s = 0; s < n; ++s)
    propagate_up(s, T.nodes.data(), T.parent_int.data(), T.parent_leaf.data(), T.mu.data(), T.amp.data(), T.sig2.data(),
                 T.agg.data(), T.flags.data());
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t i = 0; i < ni; ++i) choose_expansion(i, T.nodes.data(), T.agg.data(), tol, order, &T.herm_p[i], &T.herm_err[i]);
  int64_t total = 0;
  for (int64_t i = 0; i < ni; ++i) {
    T.herm_off[i] = total;
    total += static_cast<int64_t>(T.herm_p[i]) * T.herm_p[i];
  }
  if (total > T.coef_cap) {
    T.herm_coef.reset(new double[total]);
    T.coef_cap = total;
  }
  if (ni > T.state_cap) {
    T.herm_state.reset(new std::atomic<uint8_t>[ni]);
    T.state_cap = ni;
  }
  for (int64_t i = 0; i < ni; ++i) T.herm_state[i].store(0, std::memory_order_relaxed);
}

void check_cpu(const std::vector<at::Tensor>& ts) {
  for (const auto& t : ts) {
    TORCH_CHECK(t.device().is_cpu(), "nsplat CPU backend got a tensor on ", t.device());
    TORCH_CHECK(t.is_contiguous(), "nsplat CPU backend expects contiguous tensors");
  }
}

}  // namespace

namespace {

}  // namespace

template <typename S>
void sample_impl(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& sig2,
                 const at::Tensor& nrm, const at::Tensor& off, const at::Tensor& zc, const at::Tensor& Kd,
                 const int64_t* streams, int64_t width, int64_t height, int64_t m, double eps, int order, double tol,
                 int inclusion,
                 bool stratified, LaneSearchFn search, at::Tensor& indices, at::Tensor& probs, at::Tensor& total,
                 at::Tensor& work) {
  const int64_t B = amp.size(0), N = amp.size(1), P = width * height;
  const int nt = num_threads();
  const double log_eps = std::log(eps);
  for (int64_t b = 0; b < B; ++b) {
    const uint64_t seed = static_cast<uint64_t>(streams[2 * b]);
    const int64_t camera = streams[2 * b + 1];
    CpuTree& tree = thread_tree();
    build_tree<S>(tree, mu.data_ptr<S>() + b * N * 2, con.data_ptr<S>() + b * N * 3, amp.data_ptr<S>() + b * N,
                  sig2.data_ptr<S>() + b * N, nrm.data_ptr<S>() + b * N * 3, off.data_ptr<S>() + b * N,
                  zc.data_ptr<S>() + b * N, N, order, tol);
    TreeView tv = tree.view();
    std::vector<ItemMetric>& metric = tree.metric;
    metric.resize(std::max<int64_t>(tv.n - 1, 1));
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t i = 0; i < tv.n - 1; ++i) {  // the groups tile_items can cut: nodes of <= kGroupSize points
      const InternalNode& nd = tv.nodes[i];     // whose parent has more
      const int parent = i == 0 ? -1 : tree.parent_int[i];
      if (nd.last - nd.first + 1 <= kGroupSize &&
          (parent < 0 || tv.nodes[parent].last - tv.nodes[parent].first + 1 > kGroupSize))
        metric[i] = group_metric(tv, nd.first, nd.last);
    }
    tv.metric = metric.data();
    std::vector<double> strat_base;
    if (stratified) {  // the camera-wide uniform of each sorted point
      strat_base.resize(tv.n);
      const uint64_t stream = camera_stream(seed, camera);
      for (int64_t s = 0; s < tv.n; ++s) strat_base[s] = uniform01(stream, tv.id[s]);
    }
    const LazyHermite hermite{tree.herm_state.get(), tree.amp.data(), tree.herm_coef.get()};
    const LaneJob job{tv, hermite, stratified ? strat_base.data() : nullptr, tree.nrm.data(), tree.off.data(), tree.zc.data(),
                      Kd.data_ptr<double>() + b * 9, seed, camera, width, static_cast<int>(m), eps,
                      inclusion};
    int* idx_b = indices.data_ptr<int>() + b * P * m;
    S* prob_b = probs.data_ptr<S>() + b * P * m;
    S* total_b = total.data_ptr<S>() + b * P;
    int* work_b = work.data_ptr<int>() + b * P;
    // One task per kTileSize^2 tile: its items (tile.h), then the lane search (lanes.h) and each pixel's output.
    const int64_t tiles_x = (width + kTileSize - 1) / kTileSize, tiles_y = (height + kTileSize - 1) / kTileSize;
    const double log_theta = tile_log_theta(log_eps, static_cast<int>(m));
    const double log_far = tile_log_far(log_eps, static_cast<int>(m));
#pragma omp parallel num_threads(nt)
    {
      // a tile has at most one item per point: one pass of tile_items into a buffer of tv.n items
      std::unique_ptr<TileItem[]> items(new TileItem[std::max<int64_t>(tv.n, 1)]);
      const int cap = lane_buffer_capacity(static_cast<int>(m));
      std::vector<double> bound, suffix, out_pi(static_cast<size_t>(kLanes) * m);
      std::vector<int> order, out_id(static_cast<size_t>(kLanes) * m);
      std::vector<LaneEntry> entries(static_cast<size_t>(kLanes) * cap);
      std::vector<int32_t> hist(static_cast<size_t>(kLanes) * kHistBins);
      LaneResult res[kLanes];
#pragma omp for schedule(dynamic, 1)
      for (int64_t t = 0; t < tiles_x * tiles_y; ++t) {
        const int64_t x0 = (t % tiles_x) * kTileSize, y0 = (t / tiles_x) * kTileSize;
        const int64_t x1 = std::min(width, x0 + kTileSize), y1 = std::min(height, y0 + kTileSize);
        const double ux0 = x0 + 0.5, vy0 = y0 + 0.5, ux1 = x1 - 0.5, vy1 = y1 - 0.5;
        const int n_items = tile_items(tv, ux0, vy0, ux1, vy1, log_theta, log_far, items.get(), nullptr);
        const size_t need = std::max(n_items, 1);
        if (order.size() < need) {
          order.resize(need);
          bound.resize(need * kLanes);
          suffix.resize((need + 1) * kLanes);
        }
        const LaneScratch scratch{bound.data(),  suffix.data(), order.data(),  entries.data(),
                                  hist.data(),   cap,           out_id.data(), out_pi.data()};
        search(job, items.get(), n_items, x0, y0, static_cast<int>(x1 - x0), static_cast<int>(y1 - y0),
               scratch, res);
        for (int l = 0; l < kLanes; ++l) {
          const int64_t px = x0 + l % kTileSize, py = y0 + l / kTileSize;
          if (px >= x1 || py >= y1) continue;
          const int64_t p = py * width + px;
          int* idx = idx_b + p * m;
          S* prob = prob_b + p * m;
          for (int i = 0; i < res[l].cnt; ++i) {
            idx[i] = out_id[l * m + i];
            prob[i] = static_cast<S>(out_pi[l * m + i]);
          }
          for (int64_t i = res[l].cnt; i < m; ++i) {
            idx[i] = -1;
            prob[i] = S(0);
          }
          total_b[p] = static_cast<S>(res[l].total);
          work_b[p] = res[l].evaluated;
        }
      }
    }
  }
}

std::vector<at::Tensor> sample(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                               at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor streams, int64_t width,
                               int64_t height, int64_t samples, double eps, int64_t order, double tol,
                               int64_t inclusion, bool stratified) {
  check_cpu({mu, con, amp, sig2, nrm, off, zc, Ks});
  check_streams(streams, amp.size(0));
  const char* isa = nullptr;
  const LaneSearchFn search = lane_search("auto", &isa);
  const int64_t B = amp.size(0);
  auto opts = mu.options();
  at::Tensor indices = at::empty({B, height, width, samples}, opts.dtype(at::kInt));
  at::Tensor probs = at::empty({B, height, width, samples}, opts);
  at::Tensor total = at::empty({B, height, width, 1}, opts);
  at::Tensor work = at::empty({B, height, width, 1}, opts.dtype(at::kInt));
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_sample", [&] {
    sample_impl<scalar_t>(mu, con, amp, sig2, nrm, off, zc, Kd, streams.data_ptr<int64_t>(), width, height, samples, eps,
                          static_cast<int>(order), tol, static_cast<int>(inclusion), stratified, search, indices, probs,
                          total, work);
  });
  return {indices, probs, total, work};
}

std::string sampler_isa(std::string name) {
  const char* chosen = nullptr;
  lane_search(name.c_str(), &chosen);
  return chosen;
}

std::vector<std::string> sampler_isas() {
  int count = 0;
  const char* const* names = lane_isa_names(&count);
  return std::vector<std::string>(names, names + count);
}

template <typename S>
void composite_forward_impl(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& nrm,
                            const at::Tensor& off, const at::Tensor& zc, const at::Tensor& Kd, const at::Tensor& feat,
                            const at::Tensor& bg, const at::Tensor& indices, const at::Tensor& probs, int mode,
                            at::Tensor& image, at::Tensor& alpha, at::Tensor& depth) {
  const int64_t B = indices.size(0), H = indices.size(1), W = indices.size(2), m = indices.size(3);
  const int64_t C = feat.size(-1), P = H * W;
  const int nt = num_threads();
  for (int64_t b = 0; b < B; ++b) {
    const SplatsView<S> sv = splats_of<S>(mu, con, amp, nrm, off, zc, b);
    const double* K = Kd.data_ptr<double>() + b * 9;
    const S* fb = camera_features<S>(feat, b);
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t p = 0; p < P; ++p) {
      int64_t o = b * P + p;
      double u = double(p % W) + 0.5, v = double(p / W) + 0.5;
      Ray ray = pixel_ray(K, u, v);
      composite_pixel(sv, fb, static_cast<int>(C), bg.data_ptr<S>(), indices.data_ptr<int>() + o * m,
                      probs.data_ptr<S>() + o * m, static_cast<int>(m), S(u), S(v), ray, mode,
                      image.data_ptr<S>() + o * C, alpha.data_ptr<S>() + o, depth.data_ptr<S>() + o);
    }
  }
}

std::vector<at::Tensor> composite_forward(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm, at::Tensor off,
                                          at::Tensor zc, at::Tensor Ks, at::Tensor feat, at::Tensor bg,
                                          at::Tensor indices, at::Tensor probs, int64_t mode) {
  check_cpu({mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs});
  check_features(feat, amp);
  const int64_t B = indices.size(0), H = indices.size(1), W = indices.size(2), C = feat.size(-1);
  auto opts = mu.options();
  at::Tensor image = at::empty({B, H, W, C}, opts);
  at::Tensor alpha = at::empty({B, H, W, 1}, opts);
  at::Tensor depth = at::empty({B, H, W, 1}, opts);
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_composite_forward", [&] {
    composite_forward_impl<scalar_t>(mu, con, amp, nrm, off, zc, Kd, feat, bg, indices, probs, static_cast<int>(mode),
                                     image, alpha, depth);
  });
  return {image, alpha, depth};
}

template <typename S>
void backward_pixels_impl(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& nrm,
                          const at::Tensor& off, const at::Tensor& zc, const at::Tensor& Kd, const at::Tensor& feat,
                          const at::Tensor& bg, const at::Tensor& indices, const at::Tensor& probs, int mode,
                          int estimator, const at::Tensor& g_img, const at::Tensor& g_alpha, const at::Tensor& g_depth,
                          at::Tensor& dalpha, at::Tensor& wf, at::Tensor& bgw) {
  const int64_t B = indices.size(0), H = indices.size(1), W = indices.size(2), m = indices.size(3);
  const int64_t C = feat.size(-1), P = H * W;
  const int nt = num_threads();
  for (int64_t b = 0; b < B; ++b) {
    const SplatsView<S> sv = splats_of<S>(mu, con, amp, nrm, off, zc, b);
    const double* K = Kd.data_ptr<double>() + b * 9;
    const S* fb = camera_features<S>(feat, b);
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t p = 0; p < P; ++p) {
      int64_t o = b * P + p;
      double u = double(p % W) + 0.5, v = double(p / W) + 0.5;
      Ray ray = pixel_ray(K, u, v);
      bgw.data_ptr<S>()[o] = composite_backward_pixel(
          sv, fb, static_cast<int>(C), bg.data_ptr<S>(), indices.data_ptr<int>() + o * m,
          probs.data_ptr<S>() + o * m, static_cast<int>(m), S(u), S(v), ray, mode, estimator,
          g_img.data_ptr<S>() + o * C, g_alpha.data_ptr<S>()[o], g_depth.data_ptr<S>()[o], dalpha.data_ptr<S>() + o * m,
          wf.data_ptr<S>() + o * m);
    }
  }
}

std::vector<at::Tensor> composite_backward_pixels(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                  at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor feat,
                                                  at::Tensor bg, at::Tensor indices, at::Tensor probs, int64_t mode,
                                                  int64_t estimator, at::Tensor g_img, at::Tensor g_alpha,
                                                  at::Tensor g_depth) {
  check_cpu({mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, g_img, g_alpha, g_depth});
  check_features(feat, amp);
  const int64_t B = indices.size(0), H = indices.size(1), W = indices.size(2), m = indices.size(3);
  auto opts = mu.options();
  // pass 1 writes the filled slots, the only ones pass 2 reads (its entries): no zero fill
  at::Tensor dalpha = at::empty({B, H, W, m}, opts);
  at::Tensor wf = at::empty({B, H, W, m}, opts);
  at::Tensor bgw = at::empty({B, H, W, 1}, opts);
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_composite_backward_pixels", [&] {
    backward_pixels_impl<scalar_t>(mu, con, amp, nrm, off, zc, Kd, feat, bg, indices, probs, static_cast<int>(mode),
                                   static_cast<int>(estimator), g_img, g_alpha, g_depth, dalpha, wf, bgw);
  });
  return {dalpha, wf, bgw};
}

// Pass 2: per point, over its entries (flat slot ids sorted by (point, camera), segments seg[k]..seg[k+1]).
template <typename S>
void backward_points_impl(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& nrm,
                          const at::Tensor& off, const at::Tensor& zc, const at::Tensor& Kd, const at::Tensor& entries,
                          const at::Tensor& seg, const at::Tensor& dalpha, const at::Tensor& wf,
                          const at::Tensor& g_img, const at::Tensor& g_depth, int64_t width, int64_t height,
                          bool paper, bool per_camera, std::vector<at::Tensor>& out) {
  const int64_t N = amp.size(1), m = dalpha.size(3), C = g_img.size(3), P = width * height;
  const int64_t* ent = entries.data_ptr<int64_t>();
  const int64_t* sg = seg.data_ptr<int64_t>();
  const S* da = dalpha.data_ptr<S>();
  const S* w = wf.data_ptr<S>();
  const S* gi = g_img.data_ptr<S>();
  const S* gd = g_depth.data_ptr<S>();
  const GradRows<S> rows(out);
  const int nt = num_threads();
#pragma omp parallel num_threads(nt)
  {
    std::vector<S> gf(C);
#pragma omp for schedule(dynamic, 64)
    for (int64_t k = 0; k < N; ++k) {
      int64_t e = sg[k];
      const int64_t end = sg[k + 1];
      while (e < end) {
        const int64_t b = ent[e] / (P * m);
        const SplatsView<S> sv = splats_of<S>(mu, con, amp, nrm, off, zc, b);
        const double* K = Kd.data_ptr<double>() + b * 9;
        SplatGrad<S> g;
        std::fill(gf.begin(), gf.end(), S(0));
        int64_t count = 0;
        for (; e < end && ent[e] / (P * m) == b; ++e, ++count) {
          const int64_t flat = ent[e];
          const int64_t pix = (flat / m) % P;
          const int64_t o = b * P + pix;
          const double u = double(pix % width) + 0.5, v = double(pix / width) + 0.5;
          const Ray ray = pixel_ray(K, u, v);
          for (int64_t c = 0; c < C; ++c) gf[c] += w[flat] * gi[o * C + c];
          g.add(sv, static_cast<int>(k), S(u), S(v), ray, da[flat], w[flat] * gd[o]);
        }
        const S scale = paper ? S(1) / S(count) : S(1);
        const int64_t bk = b * N + k;
        rows.put(bk, g, scale, [](S* dst, S value) { *dst = value; });
        const int64_t fk = per_camera ? bk : k;  // [B,N,C] features: camera b's own row
        for (int64_t c = 0; c < C; ++c) rows.feat[fk * C + c] += gf[c] * scale;
      }
    }
  }
}

std::vector<at::Tensor> composite_backward_points(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor nrm,
                                                  at::Tensor off, at::Tensor zc, at::Tensor Ks, at::Tensor entries,
                                                  at::Tensor seg, at::Tensor dalpha, at::Tensor wf, at::Tensor g_img,
                                                  at::Tensor g_depth, int64_t width, int64_t height, int64_t estimator,
                                                  bool per_camera_features) {
  check_cpu({mu, con, amp, nrm, off, zc, Ks, entries, seg, dalpha, wf, g_img, g_depth});
  const int64_t B = amp.size(0), N = amp.size(1), C = g_img.size(3);
  auto opts = mu.options();
  std::vector<at::Tensor> out = {at::zeros({B, N, 2}, opts), at::zeros({B, N, 3}, opts), at::zeros({B, N}, opts),
                                 at::zeros({B, N, 3}, opts), at::zeros({B, N}, opts),    at::zeros({B, N}, opts),
                                 per_camera_features ? at::zeros({B, N, C}, opts) : at::zeros({N, C}, opts)};
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_composite_backward_points", [&] {
    backward_points_impl<scalar_t>(mu, con, amp, nrm, off, zc, Kd, entries, seg, dalpha, wf, g_img, g_depth, width,
                                   height, estimator == kPaper, per_camera_features, out);
  });
  return out;
}

// The backward's per-point order: flat ids of the filled slots of ``indices`` [B,H,W,m] (int32, -1 = empty)
// grouped by point with a stable counting sort, so within a point the slots keep their (camera, pixel, slot)
// order. O(slots + N) time, extra memory 8 bytes per filled slot (the output) + 8 bytes per point.
// Returns {entries int64 [E], seg int64 [N+1]}: point k's slots are entries[seg[k] .. seg[k+1]).
std::vector<at::Tensor> entries_by_point(at::Tensor indices, int64_t num_points) {
  check_cpu({indices});
  TORCH_CHECK(indices.scalar_type() == at::kInt, "entries_by_point: indices must be int32, got ", indices.scalar_type());
  TORCH_CHECK(num_points >= 0, "entries_by_point: num_points must be >= 0, got ", num_points);
  const int32_t* idx = indices.data_ptr<int32_t>();
  const int64_t S = indices.numel();
  at::Tensor seg = at::zeros({num_points + 1}, indices.options().dtype(at::kLong));
  int64_t* sg = seg.data_ptr<int64_t>();
  for (int64_t s = 0; s < S; ++s) {
    const int32_t k = idx[s];
    if (k < 0) continue;
    TORCH_CHECK(k < num_points, "entries_by_point: slot ", s, " holds point ", k, " >= num_points ", num_points);
    ++sg[k + 1];
  }
  for (int64_t k = 0; k < num_points; ++k) sg[k + 1] += sg[k];
  at::Tensor entries = at::empty({sg[num_points]}, seg.options());
  int64_t* ent = entries.data_ptr<int64_t>();
  std::vector<int64_t> cursor(sg, sg + num_points);
  for (int64_t s = 0; s < S; ++s) {
    const int32_t k = idx[s];
    if (k >= 0) ent[cursor[k]++] = s;
  }
  return {entries, seg};
}

}  // namespace nsplat
