// The CPU backend computes a node's Hermite coefficients on first use (tree_build.h: expansion_coefficients):
// only the far subtrees that a pixel's search opens (lanes.h: subtree_lane) read them, a small part of the tree,
// while computing all of them costs O(N log N p^2). The coefficients are a function of the node alone, so which
// thread computes them, and when, changes no bit of any result.
#pragma once
#include <atomic>
#include <thread>

#include "../core/tree_build.h"

namespace nsplat {

// One state per internal node: 0 not computed, 1 being computed, 2 ready.
struct LazyHermite {
  std::atomic<uint8_t>* state;
  const double* amp;  // [n] amplitudes of the sorted points
  double* coef;       // the tree's coefficient storage (TreeView::herm_coef)
};

// Makes node `node`'s coefficients ready (no-op for nodes without an expansion).
inline void ensure_hermite(const TreeView& T, const LazyHermite& L, int node) {
  if (T.herm_p[node] == 0) return;
  std::atomic<uint8_t>& st = L.state[node];
  uint8_t v = st.load(std::memory_order_acquire);
  if (v == 2) return;
  if (v == 0 && st.compare_exchange_strong(v, 1, std::memory_order_acq_rel)) {
    expansion_coefficients(node, T.nodes, T.agg, T.herm_p, T.herm_off, T.mu, L.amp, L.coef);
    st.store(2, std::memory_order_release);
    return;
  }
  while (st.load(std::memory_order_acquire) != 2) std::this_thread::yield();
}

}  // namespace nsplat
