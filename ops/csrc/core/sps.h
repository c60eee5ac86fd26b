// Per-pixel sequential Poisson sampling (SPS) over the radix tree.
//
// Exact SPS draws, per pixel x, the m points with the smallest xi_k = u_k / lambda_k(x). We work with
// keys log xi. The search visits tree items in decreasing order of a rigorous upper bound U_n(x) of their
// points' total size measure (tile.h: per-tile item lists, per-pixel bucketed best-first order; search_subtree
// below for a far subtree that must be opened: depth first, larger-bound child first, with the bound
// min(box bound, Hermite estimate + truncation bound) of the isotropic majorant, hermite.h). Besides the
// sample (a max-heap of the m smallest keys) the search keeps the threshold xi_(m+1), the smallest key of any
// point offered but not in the sample. Once it exists, unvisited mass is pruned while (P + U) * xi_(m+1) < eps,
// where P is the bound mass pruned so far; since xi_(m+1) only decreases, at the end P * xi_(m+1) < eps, and by
// the union bound the probability that any unvisited point would have entered the m + 1 smallest keys (so
// changed the sample or the threshold) is below eps. The total Lambda(x) is estimated as the visited exact
// mass plus estimates of the pruned mass, so |Lambda_hat - Lambda| <= P < eps / xi_(m+1).
//
// Inclusion probabilities (finalize_pixel), one of:
//   kThreshold: pi_k = min(1, lambda_k * xi_(m+1)) (priority sampling, Duffield-Lund-Thorup 2007). Given
//     the other points' keys, k is in the sample iff u_k < lambda_k * xi'_(m) where xi'_(m) is the m-th
//     smallest of the others' keys, and when it is, xi_(m+1) = xi'_(m); so pi_k is k's exact
//     conditional inclusion probability and E[1{k in S} / pi_k] = 1: Horvitz-Thompson with these
//     weights is exactly unbiased (given an exact SPS search).
//   kPips: the piPS target probabilities pi_k = min(1, c lambda_k) with sum pi = m, c solved from the
//     sampled lambdas (the largest ones are the certainty units) and Lambda_hat. SPS includes points
//     only approximately with these probabilities (Ohlsson 1998): HT with them is slightly biased.
#pragma once
#include "common.h"
#include "ewa.h"
#include "hermite.h"
#include "lbvh.h"
#include "rng.h"

namespace nsplat {

struct ItemMetric;  // tile.h

// A camera's tree; points are stored in key order (morton_key: scale class, then Morton code; double copies of
// the projected values).
struct TreeView {
  int64_t n;                  // points in the tree (valid points of this camera)
  const InternalNode* nodes;  // [n-1]
  const NodeAgg* agg;         // [n-1]
  const int* herm_p;          // [n-1], 0 = no expansion
  const int64_t* herm_off;    // [n-1] offsets into herm_coef
  const double* herm_err;     // [n-1] absolute truncation bound
  const double* herm_coef;
  const double* mu;           // [n,2]
  const double* con;          // [n,3]
  const double* logA;         // [n]
  const double* sig2;         // [n] largest principal variance
  const int* id;              // [n] original point index
  const ItemMetric* metric;     // [n-1] bound metric of the internal nodes with <= kGroupSize points (tile.h)
};

// Projected splats of one camera in the original point order (working precision S).
template <typename S>
struct SplatsView {
  const S* mu;   // [N,2]
  const S* con;  // [N,3]
  const S* amp;  // [N]
  const S* nrm;  // [N,3]
  const S* off;  // [N]
  const S* zc;   // [N]
};

NS_HD bool key_less(double ka, int ia, double kb, int ib) { return ka < kb || (ka == kb && ia < ib); }

// Heaps of (key, id) entries with a stride: entry j at key[j * stride], id[j * stride], so that several heaps can
// interleave (entry j of heap h at key[j * H + h]: the CUDA sampler's threads, one heap each, access consecutive
// addresses).

// Max-heap on (key, id). Sift-down moves a hole instead of swapping (the same result: keys are distinct pairs).
NS_HD void heap_sift_down(double* key, int* id, int64_t stride, int n, int i) {
  const double k = key[i * stride];
  const int v = id[i * stride];
  while (true) {
    int big = 2 * i + 1;
    if (big >= n) break;
    if (big + 1 < n && key_less(key[big * stride], id[big * stride], key[(big + 1) * stride], id[(big + 1) * stride]))
      ++big;
    if (!key_less(k, v, key[big * stride], id[big * stride])) break;
    key[i * stride] = key[big * stride];
    id[i * stride] = id[big * stride];
    i = big;
  }
  key[i * stride] = k;
  id[i * stride] = v;
}

NS_HD void heap_swap(double* key, int* id, int64_t stride, int a, int b) {
  const double tk = key[a * stride];
  key[a * stride] = key[b * stride];
  key[b * stride] = tk;
  const int ti = id[a * stride];
  id[a * stride] = id[b * stride];
  id[b * stride] = ti;
}

NS_HD void heap_push(double* key, int* id, int64_t stride, int n, double k, int v) {
  int i = n;
  key[i * stride] = k;
  id[i * stride] = v;
  while (i > 0) {
    int parent = (i - 1) >> 1;
    if (!key_less(key[parent * stride], id[parent * stride], key[i * stride], id[i * stride])) break;
    heap_swap(key, id, stride, i, parent);
    i = parent;
  }
}

// In-place ascending sort of (key, id) pairs.
NS_HD void heap_sort(double* key, int* id, int64_t stride, int n) {
  for (int i = n / 2 - 1; i >= 0; --i) heap_sift_down(key, id, stride, n, i);
  for (int end = n - 1; end > 0; --end) {
    heap_swap(key, id, stride, 0, end);
    heap_sift_down(key, id, stride, end, 0);
  }
}

// Upper bound (log) and estimate (linear) of internal node `node`'s total size measure at (u, v).
NS_HD void node_bound(const TreeView& T, int node, double u, double v, double* log_ub, double* est) {
  const NodeAgg& a = T.agg[node];
  double dx = dmax(dmax(a.box[0] - u, u - a.box[2]), 0.0);
  double dy = dmax(dmax(a.box[1] - v, v - a.box[3]), 0.0);
  double h2 = dmax(a.h2, 1e-300);
  double lub = a.log_amp - (dx * dx + dy * dy) / (2.0 * h2);
  int p = T.herm_p[node];
  if (p > 0) {
    double cx = 0.5 * (a.box[0] + a.box[2]), cy = 0.5 * (a.box[1] + a.box[3]);
    double h = hermite_eval(T.herm_coef + T.herm_off[node], p, cx, cy, 1.0 / sqrt(2.0 * h2), u, v);
    double ub = h + T.herm_err[node];
    double lh = ub > 0.0 ? log(ub) : -INFINITY;
    lub = dmin(lub, lh);
    *log_ub = lub;
    *est = dmin(dmax(h, 0.0), fast_exp(lub));
    return;
  }
  *log_ub = lub;
  *est = 0.5 * fast_exp(lub);
}

struct PixelStats {
  double total;     // Lambda_hat(x)
  double rest;      // log xi_(m+1), the smallest key outside the sample (+inf: every point with lambda > 0 is in)
  int evaluated;    // exact kernel evaluations (= points visited)
  int nodes;        // node bounds computed (tile items and tree nodes visited)
  bool exhaustive;  // every point of the tree was visited (nothing pruned)
};

// Optional per-pixel diagnostics of a sampling call (benchmarks): null pointers are not written.
struct SamplerCounters {
  int* nodes;  // [pixels] tree nodes visited
};

// The search state of one pixel: the sample heap, the threshold and the pruned mass.
struct PixelState {
  double* key;        // [m] max-heap of sample keys (log xi), entry j at key[j * stride]
  int* idx;           // [m] their original point ids, entry j at idx[j * stride]
  int64_t stride;
  int cnt, m;
  double visited;     // exact mass of the visited points
  double rest;        // log xi_(m+1) (+inf while there is none)
  double xi_rest;     // exp(rest)
  double log_eps;
  double budget;      // eps / xi_(m+1) = exp(log_eps - rest): the mass that may stay unvisited (0 while rest = inf)
  double log_pruned;  // log P, the bound mass pruned so far
  double pruned_est;  // estimate of the pruned mass (for Lambda_hat)
  int evaluated, nodes;
};

NS_HD PixelState pixel_state(double* key, int* idx, int64_t stride, int m, double log_eps) {
  return PixelState{key, idx, stride, 0, m, 0.0, INFINITY, INFINITY, log_eps, 0.0, -INFINITY, 0.0, 0, 0};
}

// Offers sorted point s to the sample. `rest` is the log threshold xi_(m+1) (the smallest key not in the
// sample, +inf while there is none) and `xi_rest` = exp(rest): a point with u >= xi_rest * lambda * (1 +
// 1e-12) cannot change the sample or the threshold and is rejected without computing log u; other
// candidates are compared on exact keys, so the result is the same as with exact keys everywhere.
NS_HD void offer_point(const TreeView& T, int s, double u, double v, const Draw& draw, PixelState& S) {
  double lam_log = log_size(T.mu + 2 * s, T.con + 3 * s, T.logA[s], u, v);
  double lam = fast_exp(lam_log);
  S.visited += lam;
  ++S.evaluated;
  int pid = T.id[s];
  double un = draw_uniform(draw, pid);
  if (S.cnt == S.m && un >= S.xi_rest * lam * (1.0 + 1e-12)) return;
  double k = log(un) - lam_log;
  if (S.cnt < S.m) {
    heap_push(S.key, S.idx, S.stride, S.cnt, k, pid);
    ++S.cnt;
    return;
  }
  if (key_less(k, pid, S.key[0], S.idx[0])) {
    double evicted = S.key[0];
    S.key[0] = k;
    S.idx[0] = pid;
    heap_sift_down(S.key, S.idx, S.stride, S.m, 0);
    k = evicted;
  }
  if (k < S.rest) {
    S.rest = k;
    S.xi_rest = fast_exp(k);
    S.budget = fast_exp(S.log_eps - k);
  }
}

// Depth-first search of the subtree of internal node `root` (larger-bound child first). A node is pruned
// when (P + U_n) * xi_(m+1) < eps * kDfsShare: the search spends at most that share of the budget, leaving
// the rest for the caller's pending mass (tile.h).
constexpr double kDfsShare = 0.5;

// The depth-first stack holds node ids (kStackSize of them); their bounds are kept for the top kBoundRing entries
// only, in a ring indexed by stack position (a GPU thread's stack stays small). An entry that a deeper push has
// evicted from the ring gets its bound recomputed when it is popped: node_bound is a function of the node and the
// pixel, so the search takes the same steps, bit for bit, as one that kept every bound.
constexpr int kBoundRing = 4;  // a power of two
static_assert((kBoundRing & (kBoundRing - 1)) == 0, "kBoundRing must be a power of two");

// Bounds of the ring: entry at stack position p in slot p % kBoundRing, valid for positions >= `from`.
struct BoundRing {
  double lub[kBoundRing], est[kBoundRing];
  int from;
};

// Records the bounds of the entry pushed at stack position p (evicting position p - kBoundRing).
NS_HD void ring_push(BoundRing& R, int p, double lub, double est) {
  R.lub[p & (kBoundRing - 1)] = lub;
  R.est[p & (kBoundRing - 1)] = est;
  R.from = imax(imin(R.from, p), p - kBoundRing + 1);
}

// The bounds of the entry popped from stack position p: from the ring, or recomputed when evicted.
NS_HD void ring_pop(const BoundRing& R, const TreeView& T, int node, int p, double u, double v, double* lub,
                    double* est) {
  if (p >= R.from) {
    *lub = R.lub[p & (kBoundRing - 1)];
    *est = R.est[p & (kBoundRing - 1)];
  } else {
    node_bound(T, node, u, v, lub, est);
  }
}

// A child `ref` of a node being opened: a point (ref < 0) is offered to the sample, a node gets its bound.
NS_HD void open_child(const TreeView& T, int ref, double u, double v, const Draw& draw, PixelState& S, double* lub,
                      double* est) {
  if (ref < 0) {
    offer_point(T, ~ref, u, v, draw, S);
    return;
  }
  node_bound(T, ref, u, v, lub, est);
  ++S.nodes;
}

// Pushes child `ref` with its bounds (points are not pushed: open_child offered them).
NS_HD void push_node(int* node_st, BoundRing& ring, int& sp, int ref, double lub, double est) {
  if (ref < 0) return;
  node_st[sp] = ref;
  ring_push(ring, sp, lub, est);
  ++sp;
}

NS_HD void search_subtree(const TreeView& T, int root, double u, double v, const Draw& draw, PixelState& S) {
  const double log_limit = S.log_eps + log(kDfsShare);
  int node_st[kStackSize];
  BoundRing ring;
  ring.from = 0;
  double root_lub, root_est;
  node_bound(T, root, u, v, &root_lub, &root_est);
  ring_push(ring, 0, root_lub, root_est);
  node_st[0] = root;
  ++S.nodes;
  int sp = 1;
  while (sp > 0) {
    --sp;
    const int node = node_st[sp];
    double lub, est;
    ring_pop(ring, T, node, sp, u, v, &lub, &est);
    if (S.rest < INFINITY) {
      double lp = log_add_exp(S.log_pruned, lub);
      if (lp + S.rest < log_limit) {
        S.log_pruned = lp;
        S.pruned_est += est;
        continue;
      }
    }
    const InternalNode& nd = T.nodes[node];
    if (nd.last - nd.first + 1 <= kLeafSize) {
      for (int s = nd.first; s <= nd.last; ++s) offer_point(T, s, u, v, draw, S);
      continue;
    }
    // the children in order (a point is offered at once); then the smaller bound is pushed first so that the larger
    // is visited next
    double left_lub = -INFINITY, left_est = 0.0, right_lub = -INFINITY, right_est = 0.0;
    open_child(T, nd.left, u, v, draw, S, &left_lub, &left_est);
    open_child(T, nd.right, u, v, draw, S, &right_lub, &right_est);
    if (left_lub <= right_lub) {
      push_node(node_st, ring, sp, nd.left, left_lub, left_est);
      push_node(node_st, ring, sp, nd.right, right_lub, right_est);
    } else {
      push_node(node_st, ring, sp, nd.right, right_lub, right_est);
      push_node(node_st, ring, sp, nd.left, left_lub, left_est);
    }
  }
}

// Turns the heap key/idx (entry j at [j * stride], a scratch) into the output sample out_idx/prob[0..m): inclusion
// probabilities (kThreshold from the log threshold `rest`, kPips from Lambda_hat), then slots ordered front to back
// by per-pixel depth (ties by id). Empty slots get index -1 and probability 0. When the sample holds every point
// with lambda > 0 (`all_in`, or no point outside the sample has a finite key), all probabilities are 1.
template <typename S>
NS_HD void finalize_pixel(const SplatsView<S>& P, double u, double v, const Ray& ray, int m, int cnt, double total,
                          double rest, bool all_in, int inclusion, double* key, int* idx, int64_t stride, int* out_idx,
                          S* prob) {
  if (total < kMinTotal) cnt = 0;
  double c = INFINITY;
  if (inclusion == kPips && cnt == m && !all_in && rest < INFINITY) {
    for (int i = 0; i < cnt; ++i) {
      int k = idx[i * stride];
      key[i * stride] = -exp(log_size(P.mu + 2 * k, P.con + 3 * k, log(static_cast<double>(P.amp[k])), u, v));
    }
    heap_sort(key, idx, stride, cnt);  // lambda descending
    double rest_mass = total;
    for (int j = 0; j < cnt; ++j) {
      double lam = -key[j * stride];
      double cj = (m - j) / rest_mass;
      if (cj * lam < 1.0) { c = cj; break; }
      rest_mass -= lam;
      if (rest_mass <= 1e-12 * total) break;  // the remaining mass is rounding noise: all certainty units
    }
  }
  for (int i = 0; i < cnt; ++i) {
    int k = idx[i * stride];
    bool on_plane;
    S dot;
    key[i * stride] = static_cast<double>(splat_depth(P.nrm + 3 * k, P.off[k], P.zc[k], ray, &on_plane, &dot));
  }
  heap_sort(key, idx, stride, cnt);
  const bool certain = all_in || rest == INFINITY;
  for (int i = 0; i < cnt; ++i) {
    int k = idx[i * stride];
    out_idx[i] = k;
    if (certain || (inclusion == kPips && c == INFINITY)) {
      prob[i] = S(1);
      continue;
    }
    double lam_log = log_size(P.mu + 2 * k, P.con + 3 * k, log(static_cast<double>(P.amp[k])), u, v);
    double pi = inclusion == kPips ? c * fast_exp(lam_log) : fast_exp(dmin(lam_log + rest, 0.0));
    prob[i] = static_cast<S>(dmin(1.0, pi));
  }
  for (int i = cnt; i < m; ++i) {
    out_idx[i] = -1;
    prob[i] = S(0);
  }
}

}  // namespace nsplat
