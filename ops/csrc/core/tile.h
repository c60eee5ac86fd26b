// Per-tile item lists and the per-pixel search over them (the paper's per-block expansion caching).
//
// Tile pass (once per kTileSize x kTileSize pixel tile): the tree is cut into "items" with bounds over the
// whole tile rectangle R. A node becomes an item when it holds at most kGroupSize points (a group, whose
// points are evaluated exactly when the group is visited) or when its box bound over R,
//   U_n(R) = sum_amp exp(-dist(box_n, R)^2 / (2 h^2)),
// is below theta (a far subtree, searched per pixel with search_subtree when visited). Every point of the
// tree is in exactly one item, so nothing is dropped at the tile level. Items whose bound over R is below
// a second threshold are "far": they are binned once per tile by that bound and not bounded per pixel. On a GPU
// a tile's list is cut by kTileSlots threads, one per slot (tile_slot_items: the subtrees at depth kSlotBits,
// left to right), and arranged for the pixel pass by a stable sort of the items by (tile, near/far bin).
//
// Pixel pass (sample_lane, the CUDA sampler; the CPU's tile lanes in cpu/lanes.h visit in tile order instead):
// every near item gets its bound U_i(x) at the pixel centre (the smaller of the isotropic box bound and the
// ellipse bound of ItemMetric); items are visited in decreasing bound order, bucketed in bins of kBinWidth in
// log U (stable within a bin). Before each item, with R a bound of the summed bounds of the items not yet
// visited and P the mass pruned inside subtrees, the search stops when (P + R) xi_(m+1) < eps (the remaining
// items are pruned), or when visited + P + R < kMinTotal (the pixel is certainly below the floor and stays
// empty). This spends the budget eps / xi_(m+1) on the smallest bounds only, and xi_(m+1) drops early because
// the largest lambdas come first. The guarantee is the one of sps.h: at the end P_total xi_(m+1) < eps, so the
// sample and xi_(m+1) are the exact SPS ones except with probability < eps (union bound over the unvisited
// points, whose draws are independent of the visited ones), and |Lambda_hat - Lambda| <= P_total. The draws are
// the same (a point's u depends on the pixel and the point only), only the order of the visits and the set of
// visited points change.
//
// Lanes (several threads per pixel when the image has too few pixels to fill a GPU): lane j of K searches the
// items i = j (mod K) of the tile's list alone, with the budget eps / K and the floor kMinTotal / K, keeping its
// own heap of its m smallest keys and its own threshold xi_j (the smallest of its keys outside its heap). The
// pixel's sample is the m smallest keys of the lanes' heaps (every key outside lane j's heap has m smaller keys
// in it), and xi_(m+1) the smallest key left: the next heap entry or the smallest xi_j. Every xi_j >= xi_(m+1),
// so P_total xi_(m+1) <= sum_j P_j xi_j < K eps / K = eps: the same guarantee. A lane stopped by its floor test
// has pruned mass outside its budget: when the lanes' bounds (visited + P_j) sum below kMinTotal the pixel is
// certainly below the floor and stays empty; otherwise each such lane searches again without the floor test.
// So a pixel's result is that of lanes without floor tests, or empty when certified below the floor. On a GPU
// (cuda/splat_cuda.cu) the lanes of a pixel are threads of one kernel, then of the merge kernels: one that re-searches
// and sorts each lane's heap, one that writes each heap entry at its rank in the pixel's merged order (its index plus
// the other lanes' entries before it, by binary search; rank m is xi_(m+1)'s candidate), and one per pixel that
// sums the lanes' stats: the result of merging the sorted heaps one entry at a time. Each of these kernels runs
// over the tiles of all the cameras of a group (up to kCameraGroup cameras) at once; the lane count depends on
// the image size and m only, so a camera's lanes, and so its sample, are the same alone or in a call with others.
#pragma once
#include "sps.h"

namespace nsplat {

constexpr int kGroupSize = 8;        // nodes with at most this many points are evaluated as one item
constexpr int kTileSize = 4;        // tile edge in pixels
constexpr int kBins = 120;               // log-bound bins of the pixel pass
constexpr double kBinTop = 2.0;          // upper edge of bin 0 in log U (bounds above it go to bin 0)
constexpr double kBinWidth = 0.5;        // bin width in log U
constexpr double kBinStep = 0.60653066;  // >= exp(-kBinWidth) = 0.606530659712633...
// A subtree is cut off at the tile level when its bound over the tile is below eps * kTileTheta / (m + 1)
// (a fraction of the budget eps / xi_(m+1) >= eps Lambda / (m + 1) of a pixel with Lambda ~ 1).
constexpr double kTileTheta = 1e-9;
// Items whose bound over the tile is below eps * kTileFar / (m + 1) are binned once per tile (far items).
constexpr double kTileFar = 1e-4;

// Ellipse bound of an item at a pixel: every point j of the item has q_j(x - mu_j) >= |x - mu_j|_M^2 for the
// metric M, and |mu_j - c|_M <= r, so by the triangle inequality
//   lambda_j(x) <= A_j exp(-max(0, |x - c|_M - r)^2 / 2)   and   sum_j lambda_j(x) <= sum_j A_j * (same).
struct ItemMetric {
  double cx, cy;      // centre c
  double ma, mb, mc;  // M = [[ma, mb], [mb, mc]]
  double r;           // radius of the means about c in the metric M
};

// Metric of a group of sorted points first..last: M = c_min Q, Q the mean conic of the group and c_min the
// smallest generalised eigenvalue of (Q_j, Q) over the group, so Q_j >= M for every j (Loewner order).
// Neighbouring surfels project to similar ellipses, so c_min stays close to 1 even for elongated splats,
// where the isotropic majorant exp(-|d|^2 / (2 sigma_max^2)) is loose across the short axis.
NS_HD ItemMetric group_metric(const TreeView& T, int first, int last) {
  double qa = 0.0, qb = 0.0, qc = 0.0, cx = 0.0, cy = 0.0;
  const int n = last - first + 1;
  for (int s = first; s <= last; ++s) {
    qa += T.con[3 * s]; qb += T.con[3 * s + 1]; qc += T.con[3 * s + 2];
    cx += T.mu[2 * s]; cy += T.mu[2 * s + 1];
  }
  qa /= n; qb /= n; qc /= n; cx /= n; cy /= n;
  const double dq = qa * qc - qb * qb;
  double cmin = 1.0;
  for (int s = first; s <= last; ++s) {
    const double a = T.con[3 * s], b = T.con[3 * s + 1], c = T.con[3 * s + 2];
    // det(Q_j - l Q) = dq l^2 - t l + dj = 0; smallest root 2 dj / (t + sqrt(t^2 - 4 dq dj)), no cancellation
    const double t = a * qc + c * qa - 2.0 * b * qb, dj = a * c - b * b;
    const double l = 2.0 * dj / (t + sqrt(dmax(t * t - 4.0 * dq * dj, 0.0)));
    cmin = l >= 0.0 ? dmin(cmin, l) : -1.0;  // a degenerate conic (or NaN) makes M = 0, the trivial bound
    if (cmin < 0.0) break;
  }
  cmin = dmax(cmin, 0.0) * (1.0 - 1e-9);  // rounding margin: M stays below every Q_j
  ItemMetric g{cx, cy, cmin * qa, cmin * qb, cmin * qc, 0.0};
  for (int s = first; s <= last; ++s) {
    const double dx = T.mu[2 * s] - cx, dy = T.mu[2 * s + 1] - cy;
    g.r = dmax(g.r, sqrt(dmax(g.ma * dx * dx + 2.0 * g.mb * dx * dy + g.mc * dy * dy, 0.0)));
  }
  g.r = g.r * (1.0 + 1e-9) + 1e-12;
  return g;
}

struct TileItem {
  ItemMetric g;     // ellipse bound (see ItemMetric)
  double box[4];    // box of the means
  double inv2h2;    // 1 / (2 h^2), h^2 the largest principal variance
  double log_amp;   // log of the summed amplitudes
  int ref;          // node reference (>= 0 internal node, < 0 point ~ref)
  int first, last;  // sorted points covered
  int group;        // 1: evaluate the points exactly; 0: search the subtree
  int tile_bin;     // -1: near item (bounded per pixel); >= 0: far item, binned by its bound over the tile
};

// Item of node reference `ref`. Groups (at most kGroupSize points) take their precomputed metric
// (T.metric); a single point its own conic; a larger subtree the isotropic M = I / h^2 about its box centre.
NS_HD TileItem tile_item(const TreeView& T, int ref) {
  TileItem it;
  it.ref = ref;
  it.tile_bin = -1;
  if (ref < 0) {
    int s = ~ref;
    it.g = ItemMetric{T.mu[2 * s], T.mu[2 * s + 1], T.con[3 * s], T.con[3 * s + 1], T.con[3 * s + 2], 0.0};
    it.log_amp = T.logA[s];
    it.box[0] = it.box[2] = T.mu[2 * s];
    it.box[1] = it.box[3] = T.mu[2 * s + 1];
    it.inv2h2 = 0.5 / dmax(T.sig2[s], 1e-300);
    it.first = it.last = s;
    it.group = 1;
    return it;
  }
  const NodeAgg& a = T.agg[ref];
  it.log_amp = a.log_amp;
  for (int c = 0; c < 4; ++c) it.box[c] = a.box[c];
  it.inv2h2 = 0.5 / dmax(a.h2, 1e-300);
  it.first = T.nodes[ref].first;
  it.last = T.nodes[ref].last;
  it.group = it.last - it.first + 1 <= kGroupSize;
  if (it.group) {
    it.g = T.metric[ref];
  } else {
    const double ih2 = 1.0 / dmax(a.h2, 1e-300), hx = 0.5 * (a.box[2] - a.box[0]), hy = 0.5 * (a.box[3] - a.box[1]);
    it.g = ItemMetric{0.5 * (a.box[0] + a.box[2]), 0.5 * (a.box[1] + a.box[3]), ih2, 0.0, ih2,
                      sqrt((hx * hx + hy * hy) * ih2) * (1.0 + 1e-9)};
  }
  return it;
}

// log of the bound of item `it` at pixel (u, v).
NS_HD double item_log_bound(const TileItem& it, double u, double v) {
  const double dx = u - it.g.cx, dy = v - it.g.cy;
  const double d = sqrt(dmax(it.g.ma * dx * dx + 2.0 * it.g.mb * dx * dy + it.g.mc * dy * dy, 0.0)) - it.g.r;
  const double bx = dmax(dmax(it.box[0] - u, u - it.box[2]), 0.0);
  const double by = dmax(dmax(it.box[1] - v, v - it.box[3]), 0.0);
  return it.log_amp - dmax(d > 0.0 ? 0.5 * d * d : 0.0, (bx * bx + by * by) * it.inv2h2);
}

// log of the box bound of internal node `node` over the rectangle [x0, x1] x [y0, y1].
NS_HD double node_rect_log_bound(const TreeView& T, int node, double x0, double y0, double x1, double y1) {
  const NodeAgg& a = T.agg[node];
  double dx = dmax(dmax(a.box[0] - x1, x0 - a.box[2]), 0.0);
  double dy = dmax(dmax(a.box[1] - y1, y0 - a.box[3]), 0.0);
  return a.log_amp - (dx * dx + dy * dy) / (2.0 * dmax(a.h2, 1e-300));
}

NS_HD int bound_bin(double lb);

// log of the box bound of `it` over the rectangle [x0, x1] x [y0, y1].
NS_HD double item_rect_log_bound(const TileItem& it, double x0, double y0, double x1, double y1) {
  double dx = dmax(dmax(it.box[0] - x1, x0 - it.box[2]), 0.0);
  double dy = dmax(dmax(it.box[1] - y1, y0 - it.box[3]), 0.0);
  return it.log_amp - (dx * dx + dy * dy) * it.inv2h2;
}

// Whether tree reference `ref` is an item of the tile whose pixel centres span [x0, x1] x [y0, y1]: a point, a
// group, or a subtree whose bound over the tile is below exp(log_theta).
NS_HD bool is_tile_item(const TreeView& T, int ref, double x0, double y0, double x1, double y1, double log_theta) {
  return ref < 0 || T.nodes[ref].last - T.nodes[ref].first + 1 <= kGroupSize ||
         node_rect_log_bound(T, ref, x0, y0, x1, y1) < log_theta;
}

// The item of reference `ref` for that tile: "far" (keeping the bin of its bound over the tile in tile_bin) when
// that bound is below exp(log_far).
NS_HD TileItem tile_rect_item(const TreeView& T, int ref, double x0, double y0, double x1, double y1, double log_far) {
  TileItem it = tile_item(T, ref);
  const double lt = item_rect_log_bound(it, x0, y0, x1, y1);
  if (lt < log_far && bound_bin(lt) > 0) it.tile_bin = bound_bin(lt);
  return it;
}

// Cuts the subtree of reference `root` into the items of the tile whose pixel centres span [x0, x1] x [y0, y1], in
// Morton order. Writes them to `out` when it is not null; returns their number. `nodes` (if not null) gets the tree
// nodes visited.
NS_HD int subtree_items(const TreeView& T, int root, double x0, double y0, double x1, double y1, double log_theta,
                        double log_far, TileItem* out, int* nodes) {
  int st[kStackSize];
  int sp = 0, count = 0, visited = 0;
  st[sp++] = root;
  while (sp > 0) {
    int ref = st[--sp];
    ++visited;
    if (is_tile_item(T, ref, x0, y0, x1, y1, log_theta)) {
      if (out) out[count] = tile_rect_item(T, ref, x0, y0, x1, y1, log_far);
      ++count;
      continue;
    }
    st[sp++] = T.nodes[ref].right;  // left first: items in Morton order
    st[sp++] = T.nodes[ref].left;
  }
  if (nodes) *nodes = visited;
  return count;
}

// The whole tree cut into the tile's items (subtree_items from the root).
NS_HD int tile_items(const TreeView& T, double x0, double y0, double x1, double y1, double log_theta,
                     double log_far, TileItem* out, int* nodes) {
  if (T.n == 0) return 0;
  return subtree_items(T, T.n == 1 ? ~0 : 0, x0, y0, x1, y1, log_theta, log_far, out, nodes);
}

// Slots of a tile's list, for threads that cut it in parallel: the tree's first kSlotBits levels split it into
// kTileSlots slots. Slot k follows the bits of k from the root (most significant first, 0 = left): if the path
// meets an item, the slot holds it when k is the leftmost slot under it (the rest of k's bits are 0) and nothing
// otherwise; else the slot holds the items of the subtree it reaches at depth kSlotBits. The slots in order hold
// tile_items' list in order.
constexpr int kSlotBits = 5;
constexpr int kTileSlots = 1 << kSlotBits;

// The items of slot `slot` (subtree_items' conventions, without the visit count).
NS_HD int tile_slot_items(const TreeView& T, int slot, double x0, double y0, double x1, double y1, double log_theta,
                          double log_far, TileItem* out) {
  if (T.n == 0) return 0;
  int ref = T.n == 1 ? ~0 : 0;
  for (int level = kSlotBits - 1; level >= 0; --level) {  // bits level..0 of the slot not yet followed
    if (is_tile_item(T, ref, x0, y0, x1, y1, log_theta)) {
      if (slot & ((1 << (level + 1)) - 1)) return 0;
      if (out) out[0] = tile_rect_item(T, ref, x0, y0, x1, y1, log_far);
      return 1;
    }
    ref = (slot >> level) & 1 ? T.nodes[ref].right : T.nodes[ref].left;
  }
  return subtree_items(T, ref, x0, y0, x1, y1, log_theta, log_far, out, nullptr);
}

// Layout of a tile's list for the pixel pass: near items first, then the far ones stably sorted by
// tile_bin, so that every bin's far items are contiguous and in Morton order. Copies `in` (tile_items' order)
// to `out`; returns the near count.
NS_HD int arrange_tile_items(const TileItem* in, int n, TileItem* out) {
  int near = 0;
  int count[kBins + 1];
  for (int b = 0; b <= kBins; ++b) count[b] = 0;
  for (int i = 0; i < n; ++i) {
    if (in[i].tile_bin < 0) out[near++] = in[i];
    else ++count[in[i].tile_bin + 1];
  }
  for (int b = 0; b < kBins; ++b) count[b + 1] += count[b];
  for (int i = 0; i < n; ++i)
    if (in[i].tile_bin >= 0) out[near + count[in[i].tile_bin]++] = in[i];
  return near;
}

NS_HD double tile_log_theta(double log_eps, int m) { return log_eps + log(kTileTheta / (m + 1.0)); }
NS_HD double tile_log_far(double log_eps, int m) { return log_eps + log(kTileFar / (m + 1.0)); }

NS_HD int bound_bin(double lb) {
  double b = (kBinTop - lb) * (1.0 / kBinWidth);
  return b <= 0.0 ? 0 : (b >= kBins - 1 ? kBins - 1 : static_cast<int>(b));
}

// Visits item `it` at the pixel: offers its points, or searches its subtree.
NS_HD void visit_item(const TreeView& T, const TileItem& it, double u, double v, const Draw& draw, PixelState& S) {
  if (it.group) {
    for (int s = it.first; s <= it.last; ++s) offer_point(T, s, u, v, draw, S);
  } else {
    search_subtree(T, it.ref, u, v, draw, S);
  }
}

// One step of the pixel pass before visiting an item: stops the search when the pending bound mass R plus
// the pruned mass is within the budget (kStopEps) or, with `floor` > 0, when visited + pruned + R < floor
// (kStopFloor: the searched mass is certainly below the floor). Either way R joins the pruned mass.
enum StopReason { kGoOn = 0, kStopEps = 1, kStopFloor = 2 };

NS_HD int stop_before_item(PixelState& S, double R, double log_eps, double floor) {
  const double pruned = S.log_pruned == -INFINITY ? 0.0 : fast_exp(S.log_pruned);
  if (S.visited + pruned + R < floor) {
    S.log_pruned = log_add_exp(S.log_pruned, log(R));
    S.pruned_est += 0.5 * R;
    return kStopFloor;
  }
  if (S.rest < INFINITY && pruned + R < S.budget) {  // linear pre-test; the log-domain test decides
    const double lp = log_add_exp(S.log_pruned, log(R));
    if (lp + S.rest < log_eps) {
      S.log_pruned = lp;
      S.pruned_est += 0.5 * R;
      return kStopEps;
    }
  }
  return kGoOn;
}

// Outcome of one lane's search (sample_lane); its sample is the heap key/idx[0..cnt).
struct LaneStats {
  PixelStats px;   // total: visited + pruned estimate; rest: the lane's own xi_(m+1); exhaustive: nothing pruned
  double bound;    // visited + pruned bound mass: a rigorous upper bound of the lane's items' total at the pixel
  int cnt;         // sample size (heap entries)
  bool floored;    // stopped by the floor test (its pruned mass is outside the eps budget)
};

// Items i < x of a lane: those with i % lanes == lane.
NS_HD int lane_items_below(int x, int lane, int lanes) { return x > lane ? (x - lane + lanes - 1) / lanes : 0; }

// A lane's item counts per bin, kept small for a GPU thread's stack: a byte each, saturating at kBinCountMax; a
// saturated bin is recounted exactly (lane_bin_count) where it is used.
constexpr int kBinCountMax = 0xFF;

// The lane's items in bin b: its near items whose byte in bin8 is b, and its far items whose tile_bin is b.
NS_HD int lane_bin_count(const TileItem* items, int n, int n_near, int lane, int lanes, const uint8_t* bin8,
                         int64_t bin8_stride, int b) {
  int count = 0;
  for (int i = lane; i < n_near; i += lanes) count += bin8[i * bin8_stride] == b;
  for (int i = n_near + (lane - n_near % lanes + lanes) % lanes; i < n && items[i].tile_bin <= b; i += lanes)
    count += items[i].tile_bin == b;
  return count;
}

// The bins of one lane at one pixel (sample_lane): the items' counts per bin and the pending bound masses
// suffix_b = sum_{b' >= b} count_b' top_b', with top_0 the largest near bound and top_b = top1 kBinStep^b (b >= 1, each
// product rounded in turn), summed from the last bin in use down. The sums are kept at every kSuffixSegment-th bin
// (ckpt) and a segment's are recomputed from them when the pixel pass enters it (seg), bit for bit the sums of one
// pass over all the bins: a GPU thread's stack holds a few hundred bytes instead of arrays of kBins doubles and ints.
constexpr int kSuffixSegment = 12;
constexpr int kSuffixSegments = (kBins + kSuffixSegment - 1) / kSuffixSegment;

struct LaneBins {
  const TileItem* items;
  const uint8_t* bin8;
  int64_t bin8_stride;
  int n, n_near, lane, lanes;
  int nb;                           // bins in use: every item is in a bin < nb
  double top0, top1;                // bin 0's top; top1 kBinStep^b is bin b's
  uint8_t count[kBins];             // the lane's items per bin (saturating at kBinCountMax)
  double ckpt[kSuffixSegments + 1]; // suffix_(j kSuffixSegment), 0 from nb on
  double seg[kSuffixSegment];       // suffix_b of the segment last filled
};

// The lane's items in bin b (exact).
NS_HD int bin_count(const LaneBins& L, int b) {
  return L.count[b] != kBinCountMax ? L.count[b]
                                     : lane_bin_count(L.items, L.n, L.n_near, L.lane, L.lanes, L.bin8, L.bin8_stride, b);
}

// Fills L.seg with suffix_b of segment j (bins j kSuffixSegment .. of those in use), from ckpt[j + 1].
NS_HD void fill_suffix_segment(LaneBins& L, int j) {
  const int lo = j * kSuffixSegment, hi = imin(lo + kSuffixSegment, L.nb);
  double t = L.top1;
  for (int b = 1; b <= lo; ++b) t *= kBinStep;
  for (int b = lo; b < hi; ++b) {
    if (b > lo) t *= kBinStep;
    L.seg[b - lo] = b == 0 ? L.top0 : t;
  }
  double s = L.ckpt[j + 1];
  for (int b = hi - 1; b >= lo; --b) {
    s = s + bin_count(L, b) * L.seg[b - lo];
    L.seg[b - lo] = s;
  }
}

// The checkpoints of the suffix sums, from the last segment in use down (each from the one above it).
NS_HD void fill_suffix_checkpoints(LaneBins& L) {
  const int used = (L.nb + kSuffixSegment - 1) / kSuffixSegment;
  for (int j = used; j <= kSuffixSegments; ++j) L.ckpt[j] = 0.0;
  for (int j = used - 1; j >= 0; --j) {
    fill_suffix_segment(L, j);
    L.ckpt[j] = L.seg[0];
  }
}

// suffix_(b + 1), for the pixel pass at bin b (bins in increasing order; it fills each segment on entering it).
NS_HD double suffix_after(LaneBins& L, int b) {
  if (b % kSuffixSegment == 0) fill_suffix_segment(L, b / kSuffixSegment);
  const int next = b + 1;
  if (next >= L.nb) return 0.0;
  return next % kSuffixSegment == 0 ? L.ckpt[next / kSuffixSegment] : L.seg[next % kSuffixSegment];
}

// The SPS search of pixel (u, v) over the items of lane `lane` of `lanes` (items i with i % lanes == lane of the
// tile's list, arranged by arrange_tile_items: n_near near items first): the pixel pass of the file comment
// restricted to those items. A lane alone (lanes = 1, log_eps = log eps, floor = kMinTotal) is the whole pixel's
// search. Near items are binned by their bound at the pixel, far items by their (larger) bound over the tile; a
// bin's near items are visited before its far ones, each in Morton order. The near items' bins go to one byte
// each at bin8[i * bin8_stride] (a tile's pixels interleave their bytes; each visited bin sweeps them: a per-pixel
// int scratch would not fit on a GPU). key/idx: the lane's m-entry heap (original point ids), entry j at
// [j * heap_stride] (sps.h).
//
// Bin masses need no exp per item: an item of bin b >= 1 has U <= top_b = exp(kBinTop - b kBinWidth), so
// the pending mass is R = (items left in bin b) top_b + sum_{b' > b} count_b' top_b' (bin 0 uses the largest
// bound in it). This overestimates the pending mass by less than exp(kBinWidth), with exact integer counts
// instead of running differences of floating-point sums. The per-bin state is LaneBins (a GPU thread's stack): the
// far items of a bin are found in the tile's list, which holds them sorted by bin, and the suffix sums are kept at
// checkpoints.
NS_HD LaneStats sample_lane(const TreeView& T, const TileItem* items, int n, int n_near, double u, double v,
                            const Draw& draw, int m, double log_eps, double floor, int lane, int lanes, double* key,
                            int* idx, int64_t heap_stride, uint8_t* bin8, int64_t bin8_stride) {
  LaneStats out{{0.0, INFINITY, 0, 0, true}, 0.0, 0, false};
  LaneBins L;
  L.items = items;
  L.bin8 = bin8;
  L.bin8_stride = bin8_stride;
  L.n = n;
  L.n_near = n_near;
  L.lane = lane;
  L.lanes = lanes;
  for (int b = 0; b < kBins; ++b) L.count[b] = 0;
  double lb0 = -INFINITY;  // largest near bound (bin 0's top; far items are never in bin 0)
  int nb = n > n_near ? items[n - 1].tile_bin + 1 : 0;  // far items are sorted by bin
  int own = lane_items_below(n, lane, lanes) - lane_items_below(n_near, lane, lanes);  // the lane's far items
  for (int i = lane; i < n_near; i += lanes, ++own) {
    const double lb = item_log_bound(items[i], u, v);
    const int b = bound_bin(lb);
    lb0 = dmax(lb0, lb);
    if (L.count[b] != kBinCountMax) ++L.count[b];
    nb = imax(nb, b + 1);
    bin8[i * bin8_stride] = static_cast<uint8_t>(b);
  }
  for (int i = n_near + (lane - n_near % lanes + lanes) % lanes; i < n; i += lanes) {
    const int b = items[i].tile_bin;
    if (L.count[b] != kBinCountMax) ++L.count[b];
  }
  out.px.nodes = (n_near - lane + lanes - 1) / lanes;
  // top_b >= exp(kBinTop - b kBinWidth) by a relative margin that covers the rounding of the products
  L.nb = nb;
  L.top0 = fast_exp(lb0) * (1.0 + 1e-12);
  L.top1 = exp(kBinTop) * (1.0 + 1e-12);
  fill_suffix_checkpoints(L);
  if (L.ckpt[0] < floor) {  // certainly below the floor
    out.px.exhaustive = own == 0;
    out.floored = own > 0;
    out.bound = L.ckpt[0];
    return out;
  }
  PixelState S = pixel_state(key, idx, heap_stride, m, log_eps);
  int stop = kGoOn;
  int far_at = n_near;  // bin b's first far item
  double t = L.top1;
  for (int b = 0; b < nb && stop == kGoOn; ++b) {
    if (b > 0) t *= kBinStep;
    const double top = b == 0 ? L.top0 : t, rest = suffix_after(L, b);
    int far_end = far_at;  // bin b's far items: [far_at, far_end)
    while (far_end < n && items[far_end].tile_bin == b) ++far_end;
    int left = bin_count(L, b);  // the lane's items of bin b not yet visited
    const int near_b = left - (lane_items_below(far_end, lane, lanes) - lane_items_below(far_at, lane, lanes));
    // near items of bin b, in Morton order
    for (int i = lane, found = 0; found < near_b && stop == kGoOn; i += lanes) {
      if (bin8[i * bin8_stride] != b) continue;
      ++found;
      stop = stop_before_item(S, left * top + rest, log_eps, floor);
      if (stop == kGoOn) {
        --left;
        visit_item(T, items[i], u, v, draw, S);
      }
    }
    // then its far items
    for (int i = far_at; i < far_end && stop == kGoOn; ++i) {
      if (i % lanes != lane) continue;
      stop = stop_before_item(S, left * top + rest, log_eps, floor);
      if (stop == kGoOn) {
        --left;
        visit_item(T, items[i], u, v, draw, S);
      }
    }
    far_at = far_end;
  }
  out.cnt = S.cnt;
  out.px.total = S.visited + S.pruned_est;
  out.px.rest = S.rest;
  out.px.evaluated = S.evaluated;
  out.px.nodes += S.nodes;
  out.px.exhaustive = S.log_pruned == -INFINITY;
  out.bound = S.visited + (S.log_pruned == -INFINITY ? 0.0 : exp(S.log_pruned));
  out.floored = stop == kStopFloor;
  return out;
}

}  // namespace nsplat
