// The CPU sampler's tile search, one pixel of a kTileSize x kTileSize tile per vector lane (lanes.h), compiled
// once per instruction set (lanes_<isa>.cpp) and picked at run time (lanes_dispatch.cpp). Every instruction set
// computes the same bits: lanes are independent IEEE double arithmetic, fused multiply-adds only where written
// (vfma), none contracted by the compiler. The AVX2 build needs FMA3 too (every AVX2 CPU but a few VIA ones).
#pragma once
#include <cstddef>

#include "../core/tile.h"
#include "lazy_hermite.h"

namespace nsplat {

constexpr int kLanes = kTileSize * kTileSize;

// One camera's sampling job.
struct LaneJob {
  TreeView tree;
  LazyHermite hermite;       // the tree's expansions, computed on first use
  const double* strat_base;  // [n] camera-wide uniform of each sorted point (stratified draws), else null
  const double* nrm;         // [n,3] camera-space unit normals of the sorted points (per-pixel depth),
  const double* off;         // [n] their plane offsets n.q,
  const double* zc;          // [n] and centre depths
  const double* K;           // [3,3] intrinsics (pixel rays)
  uint64_t seed;
  int64_t camera, width;
  int m;
  double eps;
  int inclusion;             // kThreshold or kPips (sps.h)
};

// A sampled point of a lane: its key u / lambda, lambda, original id and sorted index (three 64-bit words: the
// vector path scatters them as such).
struct LaneEntry {
  double key, lam;
  int id, sorted;
};

static_assert(sizeof(LaneEntry) == 24 && offsetof(LaneEntry, id) == 16 && offsetof(LaneEntry, sorted) == 20,
              "lanes.h scatters a LaneEntry as three 64-bit words");

constexpr int kHistBins = 1024;  // bins of a lane's threshold histogram (lanes.h): 256 octaves

// Per-thread scratch for a tile of n items and sample size m.
struct LaneScratch {
  double* bound;       // [n * kLanes] linear per-lane bounds of the tile's items (item order)
  double* suffix;      // [(n + 1) * kLanes] pending bound mass in visit order
  int* order;          // [n] visit order
  LaneEntry* entries;  // [kLanes * cap] per-lane candidate buffers
  int32_t* hist;       // [kLanes * kHistBins] per-lane threshold histograms
  int cap;             // buffer capacity (lane_buffer_capacity)
  int* out_id;         // [kLanes * m] each lane's sample front to back: original point ids
  double* out_pi;      //   and inclusion probabilities
};

// The candidate buffer of a lane for sample size m: entries fill its first half (purged when full), the second
// half is scratch for the final selection.
inline int lane_buffer_capacity(int m) { return 8 * (m + 1) + 32; }

// Per-lane outcome of the search; its sample is out_id / out_pi[l * m .. l * m + cnt).
struct LaneResult {
  double total;    // Lambda_hat (0 below the floor kMinTotal)
  int cnt;         // sample size (0 below the floor)
  int evaluated;   // exact kernel evaluations
};

// Searches the tile whose top-left pixel is (x0, y0) with w x h pixels in the image (lane l = row * kTileSize +
// col), over its n items (tile_items: near items have tile_bin < 0).
using LaneSearchFn = void (*)(const LaneJob& job, const TileItem* items, int n, int64_t x0, int64_t y0, int w, int h,
                              const LaneScratch& scratch, LaneResult* out);

void lane_search_base(const LaneJob&, const TileItem*, int, int64_t, int64_t, int, int, const LaneScratch&,
                      LaneResult*);
#if defined(__x86_64__)
void lane_search_avx2(const LaneJob&, const TileItem*, int, int64_t, int64_t, int, int, const LaneScratch&,
                      LaneResult*);
void lane_search_avx512(const LaneJob&, const TileItem*, int, int64_t, int64_t, int, int, const LaneScratch&,
                        LaneResult*);
#endif

// The instruction sets this build has, in increasing order ("base" is baseline x86-64 / the target's default).
const char* const* lane_isa_names(int* count);
// The search of instruction set `name` ("auto": the widest this CPU runs; env NSPLAT_CPU_SIMD overrides
// "auto"). Throws std::invalid_argument for an unknown name or one this CPU cannot run.
LaneSearchFn lane_search(const char* name, const char** chosen);

}  // namespace nsplat
