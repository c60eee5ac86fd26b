// Per-element steps of the tree construction, shared by the CPU and CUDA builders:
//   1. keys: morton_key per valid point, sort (backend), gather sorted point arrays (backend)
//   2. build_internal_node per internal node (independent)
//   3. propagate_up per leaf: bottom-up aggregates; the second arrival at a node computes it
//   4. choose_expansion per internal node; 5. offsets = exclusive scan of p^2 (backend)
//   6. expansion_coefficients per internal node
#pragma once
#include "common.h"
#include "hermite.h"
#include "lbvh.h"

// Device intrinsics only in nvcc's device pass (__CUDA_ARCH__): propagate_up is __host__ __device__, and its
// host instantiation (g++, or nvcc's host pass) uses the GCC atomics.
#if defined(__CUDA_ARCH__)
#define NS_ATOMIC_INC(ptr) (__threadfence(), atomicAdd((ptr), 1))
#define NS_FENCE() __threadfence()
#else
#define NS_ATOMIC_INC(ptr) __atomic_fetch_add((ptr), 1, __ATOMIC_ACQ_REL)
#define NS_FENCE() __atomic_thread_fence(__ATOMIC_SEQ_CST)
#endif

namespace nsplat {

NS_HD void build_internal_node(const uint64_t* keys, int64_t n, int64_t i, InternalNode* nodes, int* parent_int,
                               int* parent_leaf) {
  InternalNode nd = karras_node(keys, n, i);
  nodes[i] = nd;
  if (nd.left >= 0) parent_int[nd.left] = static_cast<int>(i); else parent_leaf[~nd.left] = static_cast<int>(i);
  if (nd.right >= 0) parent_int[nd.right] = static_cast<int>(i); else parent_leaf[~nd.right] = static_cast<int>(i);
}

NS_HD NodeAgg child_agg(int c, const NodeAgg* agg, const double* mu, const double* amp, const double* sig2) {
  if (c >= 0) return agg[c];
  NodeAgg a;
  int s = ~c;
  agg_point(&a, mu[2 * s], mu[2 * s + 1], amp[s], sig2[s]);
  return a;
}

// Walks from leaf s to the root; `flags` must be zeroed. Returns nothing; aggregates land in `agg`.
NS_HD void propagate_up(int64_t s, const InternalNode* nodes, const int* parent_int, const int* parent_leaf,
                        const double* mu, const double* amp, const double* sig2, NodeAgg* agg, int* flags) {
  int node = parent_leaf[s];
  while (true) {
    if (NS_ATOMIC_INC(&flags[node]) == 0) return;  // first child to arrive: the sibling finishes the node
    NS_FENCE();
    const InternalNode& nd = nodes[node];
    NodeAgg a = child_agg(nd.left, agg, mu, amp, sig2);
    NodeAgg b = child_agg(nd.right, agg, mu, amp, sig2);
    agg_merge(&agg[node], a, b);
    NS_FENCE();
    if (node == 0) return;
    node = parent_int[node];
  }
}

// Expansion order and absolute truncation bound of internal node i (0 = no expansion).
NS_HD void choose_expansion(int64_t i, const InternalNode* nodes, const NodeAgg* agg, double tol, int pmax, int* p_out,
                            double* err_out) {
  const InternalNode& nd = nodes[i];
  const NodeAgg& a = agg[i];
  *p_out = 0;
  *err_out = 0.0;
  if (nd.last - nd.first + 1 <= kLeafSize || pmax <= 0) return;
  double h = sqrt(dmax(a.h2, 1e-300));
  double rho = 0.5 * dmax(a.box[2] - a.box[0], a.box[3] - a.box[1]) / h;
  int p = hermite_order(rho, tol, pmax);
  *p_out = p;
  if (p > 0) *err_out = hermite_rel_error(rho, p) * a.sum_amp;
}

NS_HD void expansion_coefficients(int64_t i, const InternalNode* nodes, const NodeAgg* agg, const int* herm_p,
                                  const int64_t* herm_off, const double* mu, const double* amp, double* coef) {
  int p = herm_p[i];
  if (p <= 0) return;
  const NodeAgg& a = agg[i];
  double* c = coef + herm_off[i];
  for (int t = 0; t < p * p; ++t) c[t] = 0.0;
  double cx = 0.5 * (a.box[0] + a.box[2]), cy = 0.5 * (a.box[1] + a.box[3]);
  double inv = 1.0 / sqrt(2.0 * dmax(a.h2, 1e-300));
  for (int s = nodes[i].first; s <= nodes[i].last; ++s) hermite_accumulate(c, p, cx, cy, inv, mu[2 * s], mu[2 * s + 1], amp[s]);
}

}  // namespace nsplat
