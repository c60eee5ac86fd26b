// Binary radix tree over the sort keys (scale class, then the Morton code of the projected mean: morton_key)
// of a camera's splats (Karras 2012), built in parallel:
// every internal node is determined independently from the sorted unique 64-bit keys, then node
// aggregates are propagated bottom-up (the second child to arrive at a parent computes it).
//
// Layout: internal nodes 0..n-2 (root 0), leaves 0..n-1 = sorted points. A child reference c >= 0
// is an internal node, c < 0 is leaf ~c.
#pragma once
#include "common.h"

namespace nsplat {

// 15-bit quantised coordinates interleaved into a 30-bit Morton code.
NS_HD uint32_t spread_bits15(uint32_t x) {
  x &= 0x7FFFu;
  x = (x | (x << 8)) & 0x00FF00FFu;
  x = (x | (x << 4)) & 0x0F0F0F0Fu;
  x = (x | (x << 2)) & 0x33333333u;
  x = (x | (x << 1)) & 0x55555555u;
  return x;
}

// Scale class of a splat from its largest principal variance sig2 (pixels^2): 0 below a std-dev of
// kScaleClassBase pixels, then one class per factor 4 in std-dev (2, 8, 32 px and above). The class leads the
// sort key, so the tree splits by class first and space second: a splat far larger than its neighbours no
// longer shares a node with them. A node's bounds use its largest variance (NodeAgg::h2, the group metric of
// tile.h), so one huge splat in a node of small ones would make the bounds of that node and all its ancestors
// loose wherever the huge kernel reaches, and every pixel there would evaluate the small ones exactly.
constexpr double kScaleClassBase = 2.0;
NS_HD uint32_t scale_class(double sig2) {
  const double b2 = kScaleClassBase * kScaleClassBase;
  return (sig2 >= b2 ? 1u : 0u) + (sig2 >= 16.0 * b2 ? 1u : 0u) + (sig2 >= 256.0 * b2 ? 1u : 0u);
}

// Sort key of a point: its scale class (top 2 bits), the Morton code of its mean in the box [lo, lo + extent]
// (next 30 bits), its original index (low 32 bits) to make keys unique.
NS_HD uint64_t morton_key(double x, double y, double sig2, double lox, double loy, double inv_ext, int64_t id) {
  double fx = (x - lox) * inv_ext, fy = (y - loy) * inv_ext;
  fx = dmin(dmax(fx, 0.0), 1.0);
  fy = dmin(dmax(fy, 0.0), 1.0);
  uint32_t qx = static_cast<uint32_t>(fx * 32767.0), qy = static_cast<uint32_t>(fy * 32767.0);
  uint64_t code = (static_cast<uint64_t>(scale_class(sig2)) << 30) | (static_cast<uint64_t>(spread_bits15(qx)) << 1) |
                  spread_bits15(qy);
  return (code << 32) | static_cast<uint64_t>(static_cast<uint32_t>(id));
}

NS_HD int key_delta(const uint64_t* keys, int64_t n, int64_t i, int64_t j) {
  if (j < 0 || j >= n) return -1;
  return clz64(keys[i] ^ keys[j]);
}

struct InternalNode {
  int left, right;   // child references (>= 0 internal, < 0 leaf ~c)
  int first, last;   // range of sorted points covered
};

// Karras (2012), Fig. 4: children and range of internal node i of a tree over n >= 2 unique keys.
NS_HD InternalNode karras_node(const uint64_t* keys, int64_t n, int64_t i) {
  int d = key_delta(keys, n, i, i + 1) - key_delta(keys, n, i, i - 1) >= 0 ? 1 : -1;
  int dmin_ = key_delta(keys, n, i, i - d);
  int64_t lmax = 2;
  while (key_delta(keys, n, i, i + lmax * d) > dmin_) lmax <<= 1;
  int64_t l = 0;
  for (int64_t t = lmax >> 1; t >= 1; t >>= 1)
    if (key_delta(keys, n, i, i + (l + t) * d) > dmin_) l += t;
  int64_t j = i + l * d;
  int dnode = key_delta(keys, n, i, j);
  int64_t s = 0, t = l;
  do {
    t = (t + 1) >> 1;
    if (key_delta(keys, n, i, i + (s + t) * d) > dnode) s += t;
  } while (t > 1);
  int64_t gamma = i + s * d + (d < 0 ? -1 : 0);
  InternalNode node;
  node.first = static_cast<int>(i < j ? i : j);
  node.last = static_cast<int>(i < j ? j : i);
  node.left = node.first == gamma ? ~static_cast<int>(gamma) : static_cast<int>(gamma);
  node.right = node.last == gamma + 1 ? ~static_cast<int>(gamma + 1) : static_cast<int>(gamma + 1);
  return node;
}

// Aggregates of a subtree used by the sampler's bounds.
struct NodeAgg {
  double box[4];  // min x, min y, max x, max y of the means
  double sum_amp; // sum of amplitudes A (upper bound of each lambda's peak)
  double log_amp; // log(sum_amp)
  double h2;      // largest principal variance among the points (isotropic majorant bandwidth^2)
};

NS_HD void agg_point(NodeAgg* a, double x, double y, double amp, double sig2) {
  a->box[0] = a->box[2] = x;
  a->box[1] = a->box[3] = y;
  a->sum_amp = amp;
  a->log_amp = log(amp);
  a->h2 = sig2;
}

NS_HD void agg_merge(NodeAgg* out, const NodeAgg& a, const NodeAgg& b) {
  out->box[0] = dmin(a.box[0], b.box[0]);
  out->box[1] = dmin(a.box[1], b.box[1]);
  out->box[2] = dmax(a.box[2], b.box[2]);
  out->box[3] = dmax(a.box[3], b.box[3]);
  out->sum_amp = a.sum_amp + b.sum_amp;
  out->log_amp = log(out->sum_amp);
  out->h2 = dmax(a.h2, b.h2);
}

}  // namespace nsplat
