// The CPU sampler's tile search (lanes_api.h): the 16 pixels of a 4 x 4 tile share one walk over the tile's items,
// one pixel per vector lane. Included once per instruction set by lanes_<isa>.cpp after its
// `#pragma GCC target`, with NS_LANE_SEARCH naming the entry point; everything else here has internal linkage,
// so the copies compiled for different instruction sets never meet at link time.
//
// Algorithm (docs/op.md §3). The tile's items (tile.h: groups of <= 8 points, far subtrees) get a rigorous
// upper bound of their size measure at every lane's pixel (item_log_bound, vectorised); they are visited in
// decreasing order of their largest bound over the tile (bins of kBinWidth in log U; within a bin near items
// before far ones, each in Morton order). Every lane keeps its own SPS state: the heap of its m smallest keys
// xi = u / lambda, the threshold xi_(m+1) (the smallest key outside the sample), the visited exact mass and the
// pruned bound mass P. Before each item, with R the lane's bound mass of the items not yet visited (exact suffix
// sums in visit order), a lane stops when (P + R) xi_(m+1) < eps, or when visited + P + R < kMinTotal (below
// the floor: the pixel stays empty); the walk ends when every lane has stopped. So each lane meets the
// guarantee of sps.h: at the end P xi_(m+1) < eps, and its sample and threshold are the exact SPS ones except
// with probability < eps (union bound over its unvisited points). A visited group's points are evaluated for
// all lanes at once: lambda = min(alpha_max, A exp(-q / 2)) in double, the point's draw u from two 32-bit
// hashes (rng.h). A lane is a candidate when u could be below xi_(m+1) lambda, tested on the high hash alone
// (u >= hi 2^-32); candidates, a few per pixel once the heap is full, are settled exactly one by one with the
// full-precision u. Far subtrees are searched depth first per lane (rare: their bound over the tile is tiny).
//
// The per-lane arithmetic is the same IEEE double operations on every instruction set (the build disables the
// compiler's contraction into FMA; the kernel's quadratic form and the exponential's polynomial use explicit
// fused multiply-adds, vfma: hardware on AVX2 and AVX-512, the correctly rounded std::fma on the base set), so
// the samples, probabilities and totals are bitwise identical whatever the vector width (tests/test_op_sampler.py).
#if !defined(NS_LANE_SEARCH) || !defined(NS_LANE_ISA)
#error "lanes.h is included by lanes_<isa>.cpp, which define NS_LANE_SEARCH and NS_LANE_ISA"
#endif
// NS_LANE_ISA: 3 AVX-512 (F, DQ), 2 AVX2, 1 SSE2, 0 plain C++ (GCC does not update the __AVX2__-style macros
// under `#pragma GCC target`, so the translation unit says which instructions it was given).

namespace nsplat {
namespace {

#if NS_LANE_ISA == 3
constexpr int kW = 8;
#elif NS_LANE_ISA == 2
constexpr int kW = 4;
#else
constexpr int kW = 2;
#endif
constexpr int kC = kLanes / kW;  // vectors per tile
typedef double VD __attribute__((vector_size(8 * kW)));
typedef int64_t VL __attribute__((vector_size(8 * kW)));
typedef uint64_t VQ __attribute__((vector_size(8 * kW)));
typedef uint32_t VU __attribute__((vector_size(4 * kW)));

inline uint32_t movemask(VL m) {
#if NS_LANE_ISA == 3
  return _mm512_movepi64_mask(reinterpret_cast<__m512i>(m));
#elif NS_LANE_ISA == 2
  return static_cast<uint32_t>(_mm256_movemask_pd(reinterpret_cast<__m256d>(m)));
#elif NS_LANE_ISA == 1
  return static_cast<uint32_t>(_mm_movemask_pd(reinterpret_cast<__m128d>(m)));
#else
  uint32_t r = 0;
  for (int j = 0; j < kW; ++j) r |= static_cast<uint32_t>(m[j] != 0) << j;
  return r;
#endif
}

inline VD vsqrt(VD x) {
#if NS_LANE_ISA == 3
  return reinterpret_cast<VD>(_mm512_sqrt_pd(reinterpret_cast<__m512d>(x)));
#elif NS_LANE_ISA == 2
  return reinterpret_cast<VD>(_mm256_sqrt_pd(reinterpret_cast<__m256d>(x)));
#elif NS_LANE_ISA == 1
  return reinterpret_cast<VD>(_mm_sqrt_pd(reinterpret_cast<__m128d>(x)));
#else
  VD r;
  for (int j = 0; j < kW; ++j) r[j] = sqrt(x[j]);
  return r;
#endif
}

// a * b + c rounded once (fused multiply-add; the base instruction set calls the correctly rounded std::fma, so
// every instruction set computes the same bits).
inline VD vfma(VD a, VD b, VD c) {
#if NS_LANE_ISA == 3
  return reinterpret_cast<VD>(_mm512_fmadd_pd(reinterpret_cast<__m512d>(a), reinterpret_cast<__m512d>(b),
                                              reinterpret_cast<__m512d>(c)));
#elif NS_LANE_ISA == 2
  return reinterpret_cast<VD>(_mm256_fmadd_pd(reinterpret_cast<__m256d>(a), reinterpret_cast<__m256d>(b),
                                              reinterpret_cast<__m256d>(c)));
#else
  VD r;
  for (int j = 0; j < kW; ++j) r[j] = std::fma(a[j], b[j], c[j]);
  return r;
#endif
}

inline VD bcast(double x) {
  VD v;
  for (int j = 0; j < kW; ++j) v[j] = x;
  return v;
}

inline VU bcast_u(uint32_t x) {
  VU v;
  for (int j = 0; j < kW; ++j) v[j] = x;
  return v;
}

inline VD vmax(VD a, VD b) { return a > b ? a : b; }
inline VD vmin(VD a, VD b) { return a < b ? a : b; }

// Lanes of vector c whose bit is set in `bits` (bit l of the tile = lane l), as a comparison mask.
inline VL lane_mask(uint32_t bits, int c) {
  VL one, sel;
  for (int j = 0; j < kW; ++j) {
    one[j] = int64_t(1) << j;
    sel[j] = static_cast<int64_t>(bits >> (c * kW));
  }
  return (one & sel) != 0;
}

// exp(x) for x <= 709 (0 below -708): 2^(n/16) e^r with n = round(16 x / ln 2), r = x - n ln2/16 (two-constant
// reduction, n kLn2Hi exact), |r| <= ln2/32; 2^(n/16) = 2^(n >> 4) T[n & 15] with T[j] = 2^(j/16) correctly
// rounded, e^r by its Taylor polynomial of degree 7 (truncation < 2e-18 relative): within a few ulp of exp
// (tests/test_op_sampler.py). The same operations in lane_exp (vectors) and lane_exp1 (scalars).
constexpr double kExp16 = 23.083120654223414;              // 16 / ln 2
constexpr double kLn2Hi = 0.043321698780346196;            // ln2 / 16, low 20 bits zero
constexpr double kLn2Lo = 4.650385693757748e-12;           // ln2 / 16 - kLn2Hi
constexpr double kExpShift = 6755399441055744.0 + 16368.0;  // 1.5 2^52 + 16 * 1023: rounds, biases the exponent
alignas(64) constexpr double kExp2Sixteenths[16] = {
    1.0,                1.0442737824274138, 1.0905077326652577, 1.1387886347566916,
    1.189207115002721,  1.241857812073484,  1.2968395546510096, 1.3542555469368927,
    1.4142135623730951, 1.4768261459394993, 1.5422108254079407, 1.6104903319492543,
    1.681792830507429,  1.7562521603732995, 1.8340080864093424, 1.9152065613971474};
constexpr double kInvFact[8] = {1.0, 1.0, 0.5, 1.0 / 6.0, 1.0 / 24.0, 1.0 / 120.0, 1.0 / 720.0, 1.0 / 5040.0};

inline VD exp2_sixteenths(VL j) {  // kExp2Sixteenths[j] per lane
#if NS_LANE_ISA == 3
  const __m512d lo = _mm512_load_pd(kExp2Sixteenths), hi = _mm512_load_pd(kExp2Sixteenths + 8);
  return reinterpret_cast<VD>(_mm512_permutex2var_pd(lo, reinterpret_cast<__m512i>(j), hi));
#elif NS_LANE_ISA == 2
  return reinterpret_cast<VD>(_mm256_i64gather_pd(kExp2Sixteenths, reinterpret_cast<__m256i>(j), 8));
#else
  VD r;
  for (int i = 0; i < kW; ++i) r[i] = kExp2Sixteenths[j[i]];
  return r;
#endif
}

inline VD lane_exp(VD x) {
  const VD kd = vfma(x, bcast(kExp16), bcast(kExpShift));
  const VD n = kd - kExpShift;
  const VD r = (x - n * kLn2Hi) - n * kLn2Lo;
  VD p = bcast(kInvFact[7]);
  for (int k = 6; k >= 0; --k) p = vfma(p, r, bcast(kInvFact[k]));
  const VQ bits = reinterpret_cast<VQ>(kd);
  const VD scale = reinterpret_cast<VD>((bits >> 4) << 52);
  const VD y = (exp2_sixteenths(reinterpret_cast<VL>(bits & 15)) * scale) * p;
  return x < -708.0 ? bcast(0.0) : y;
}

inline double lane_exp1(double x) {
  const double kd = std::fma(x, kExp16, kExpShift);
  const double n = kd - kExpShift;
  const double r = (x - n * kLn2Hi) - n * kLn2Lo;
  double p = kInvFact[7];
  for (int k = 6; k >= 0; --k) p = std::fma(p, r, kInvFact[k]);
  uint64_t bits;
  std::memcpy(&bits, &kd, sizeof bits);
  const uint64_t sbits = (bits >> 4) << 52;
  double scale;
  std::memcpy(&scale, &sbits, sizeof scale);
  const double y = (kExp2Sixteenths[bits & 15] * scale) * p;
  return x < -708.0 ? 0.0 : y;
}

// An upper bound of exp(x), at most 2^(1.5/16) (6.7 %) above it, by the table alone: 2^((n + 1)/16) with n the
// rounded 16 x / ln 2 (so (n + 1)/16 > x / ln 2); the table's rounding is within kBoundMargin. 0 below -708 (callers
// raise bounds to kBoundFloor >= exp(-708)). For the pending-mass bounds, where the polynomial would buy nothing.
inline VD bound_exp(VD x) {
  const VQ bits = reinterpret_cast<VQ>(x * kExp16 + kExpShift + 1.0);
  const VD y = exp2_sixteenths(reinterpret_cast<VL>(bits & 15)) * reinterpret_cast<VD>((bits >> 4) << 52);
  return x < -708.0 ? bcast(0.0) : y;
}

inline double bound_exp1(double x) {
  const double kd = x * kExp16 + kExpShift + 1.0;
  uint64_t bits;
  std::memcpy(&bits, &kd, sizeof bits);
  const uint64_t sbits = (bits >> 4) << 52;
  double scale;
  std::memcpy(&scale, &sbits, sizeof scale);
  return x < -708.0 ? 0.0 : kExp2Sixteenths[bits & 15] * scale;
}

inline VU lane_hash(VU x) {
  x ^= x >> 16;
  x *= 0x7FEB352Du;
  x ^= x >> 15;
  x *= 0x846CA68Bu;
  return x ^ (x >> 16);
}

constexpr double kLogAlphaMax = -0.01005033585350145;  // log(kAlphaMax)
constexpr double kBoundMargin = 1.0 + 1e-12;            // covers the rounding of a bound's exp and of its sums
constexpr double kBoundFloor = 1e-300;                  // bounds below this are raised to it (no underflow)

// The tile's per-lane search state (lane l = vector l / kW, element l % kW).
struct Tile {
  VD U[kC], V[kC];     // pixel centres
  VU a[kC];            // low words of the pixel streams (draw_hi)
  VU b[kC];            // high words (draw_lo)
  VD shift[kC];        // stratified: lattice shifts
  VD thr[kC];          // xi_(m+1), +inf while the lane has seen at most m points
  VD vis[kC];          // visited exact mass
  VD pru[kC];          // pruned bound mass P
  VD est[kC];          // estimate of the pruned mass
  VL evals[kC];        // exact evaluations
  VL act[kC];          // lanes still searching (mask), and as bits:
  uint32_t active;
  VL lane_id[kC];      // l
  VL cnt[kC];          // candidate buffer sizes
  VL top[kC];          // threshold bin (window index; -1 while the lane has at most m entries)
  VL below[kC];        // entries in bins below `top`
  VL base[kC];         // absolute bin of window index 0
  VL low[kC];          // lowest window index counted since the histogram was last cleared (kHistBins: none)
};

inline double& lane(VD* v, int l) { return reinterpret_cast<double*>(v)[l]; }
inline double lane(const VD* v, int l) { return reinterpret_cast<const double*>(v)[l]; }
inline int64_t& lane(VL* v, int l) { return reinterpret_cast<int64_t*>(v)[l]; }
inline int64_t lane(const VL* v, int l) { return reinterpret_cast<const int64_t*>(v)[l]; }

// Masked scatters and gathers of lane values (AVX-512: one instruction; otherwise lane by lane, same result).
inline void scatter_q(int64_t* base, VL idx, VL v, VL mask) {
#if NS_LANE_ISA == 3
  _mm512_mask_i64scatter_epi64(base, static_cast<__mmask8>(movemask(mask)), reinterpret_cast<__m512i>(idx),
                               reinterpret_cast<__m512i>(v), 8);
#else
  for (int j = 0; j < kW; ++j)
    if (mask[j]) base[idx[j]] = v[j];
#endif
}

inline void scatter_d(double* base, VL idx, VD v, VL mask) {
  scatter_q(reinterpret_cast<int64_t*>(base), idx, reinterpret_cast<VL>(v), mask);
}

inline VL gather_h(const int32_t* base, VL idx, VL mask) {
#if NS_LANE_ISA == 3
  const __m256i g = _mm512_mask_i64gather_epi32(_mm256_setzero_si256(), static_cast<__mmask8>(movemask(mask)),
                                                reinterpret_cast<__m512i>(idx), base, 4);
  return reinterpret_cast<VL>(_mm512_cvtepi32_epi64(g));
#else
  VL r = VL{};
  for (int j = 0; j < kW; ++j)
    if (mask[j]) r[j] = base[idx[j]];
  return r;
#endif
}

inline void scatter_h(int32_t* base, VL idx, VL v, VL mask) {
#if NS_LANE_ISA == 3
  _mm512_mask_i64scatter_epi32(base, static_cast<__mmask8>(movemask(mask)), reinterpret_cast<__m512i>(idx),
                               _mm512_cvtepi64_epi32(reinterpret_cast<__m512i>(v)), 4);
#else
  for (int j = 0; j < kW; ++j)
    if (mask[j]) base[idx[j]] = static_cast<int32_t>(v[j]);
#endif
}

// Candidate buffers. A lane appends every candidate whose key is below its threshold; the threshold is the upper
// edge of a histogram bin at or above the one that holds the lane's (m+1)-th smallest key so far (bins of 1/4
// octave: a key's bin is its bit pattern >> kHistShift; lowered to that bin once kWalkSlack more entries lie
// below it), so it bounds that key from above and only decreases.
// The histogram covers a window of kHistBins bins below the lane's first threshold (smaller keys count in bin 0).
// A full buffer drops the entries above the threshold; the exact sample and xi_(m+1) are selected at the end.
constexpr int kHistShift = 50;
constexpr int kMaxRankSort = 128;  // samples up to this size are ordered by rank counting (vectorised)

inline int64_t key_bin(double key) {
  int64_t b;
  std::memcpy(&b, &key, sizeof b);
  return b >> kHistShift;
}

inline double bin_top(int64_t bin) {  // upper edge of absolute bin `bin`
  const int64_t b = (bin + 1) << kHistShift;
  double d;
  std::memcpy(&d, &b, sizeof d);
  return d;
}

inline int window_bin(int64_t base, double key) {
  const int64_t b = key_bin(key) - base;
  return b < 0 ? 0 : static_cast<int>(b);
}

inline LaneEntry* lane_entries(const LaneScratch& s, int l) { return s.entries + static_cast<int64_t>(l) * s.cap; }
inline int32_t* lane_hist(const LaneScratch& s, int l) { return s.hist + static_cast<int64_t>(l) * kHistBins; }

// A lane's histogram is all zero when its tile starts and when its threshold (re)starts: the counted bins are
// cleared afterwards, from the lowest counted one (`low`) to the window's top, rather than the whole window
// before (a lane's keys span a few octaves of the window's 128).
inline void clear_hist(Tile& t, const LaneScratch& s, int l) {
  int64_t& low = lane(t.low, l);
  if (low < kHistBins) std::memset(lane_hist(s, l) + low, 0, sizeof(int32_t) * (kHistBins - low));
  low = kHistBins;
}

// Builds lane l's histogram (all zero) from its first m + 1 entries: the threshold bin is the bin of their
// largest key.
inline void start_threshold(Tile& t, const LaneScratch& s, int m, int l) {
  const LaneEntry* e = lane_entries(s, l);
  double top = e[0].key;
  for (int i = 1; i <= m; ++i) top = dmax(top, e[i].key);
  int32_t* h = lane_hist(s, l);
  const int64_t base = key_bin(top) - (kHistBins - 1);
  int64_t low = kHistBins;
  for (int i = 0; i <= m; ++i) {
    const int b = window_bin(base, e[i].key);
    ++h[b];
    low = b < low ? b : low;
  }
  lane(t.low, l) = low;
  lane(t.base, l) = base;
  lane(t.top, l) = kHistBins - 1;
  lane(t.below, l) = m + 1 - h[kHistBins - 1];
  lane(t.thr, l) = bin_top(base + kHistBins - 1);
}

// Keeps lane l's m + 1 smallest entries (by (key, id)) and restarts its histogram below the largest of them.
inline void rebase(Tile& t, const LaneScratch& s, int m, int l) {
  LaneEntry* e = lane_entries(s, l);
  std::nth_element(e, e + m, e + lane(t.cnt, l), [](const LaneEntry& a, const LaneEntry& b) {
    return key_less(a.key, a.id, b.key, b.id);
  });
  lane(t.cnt, l) = m + 1;
  clear_hist(t, s, l);
  start_threshold(t, s, m, l);
}

// Drops lane l's entries above its threshold bin; if that leaves more than half of the filling part (cap / 2)
// in use (many keys in the threshold bin), rebases it.
inline void purge(Tile& t, const LaneScratch& s, int m, int l) {
  LaneEntry* e = lane_entries(s, l);
  const int64_t base = lane(t.base, l), top = lane(t.top, l);
  int n = 0;
  for (int i = 0; i < lane(t.cnt, l); ++i) {
    e[n] = e[i];
    n += window_bin(base, e[i].key) <= top;
  }
  lane(t.cnt, l) = n;
  if (4 * n > s.cap) rebase(t, s, m, l);
}

// Lowers lane l's threshold bin to the bin of its (m+1)-th smallest key (while more than m entries lie below it),
// skipping empty 8-bin blocks.
inline void lower_threshold(Tile& t, const LaneScratch& s, int m, int l) {
  int64_t& top = lane(t.top, l);
  int64_t& below = lane(t.below, l);
  const int32_t* h = lane_hist(s, l);
  do {
    while (top >= 8 && (top & 7) == 0) {
      uint64_t w[4];
      std::memcpy(w, h + top - 8, sizeof w);
      if (w[0] | w[1] | w[2] | w[3]) break;
      top -= 8;
    }
    --top;
    below -= h[top];
  } while (below > m);
  lane(t.thr, l) = bin_top(lane(t.base, l) + top);
}

// The threshold is lowered once more than m + kWalkSlack entries lie below its bin (lazily: until then it is a
// looser upper bound of xi_(m+1), which the stop test and the candidate test may use; the final selection lowers
// it exactly).
constexpr int kWalkSlack = 4;

// After lane l appended an entry: starts its threshold when it holds m + 1 entries, lowers the threshold bin when
// more than m + kWalkSlack entries lie below it (a threshold fallen to bin 0, below the window, restarts lower),
// and purges a full buffer.
inline void fix_lane(Tile& t, const LaneScratch& s, int m, int l) {
  const int64_t top = lane(t.top, l);
  const int64_t cnt = lane(t.cnt, l);
  if (top < 0) {
    if (cnt == m + 1) start_threshold(t, s, m, l);
    return;
  }
  const int64_t below = lane(t.below, l);
  if (below > m + kWalkSlack || (cnt == s.cap / 2 && below > m)) {  // a full buffer is purged below the exact bin
    lower_threshold(t, s, m, l);
    if (lane(t.top, l) == 0) {
      purge(t, s, m, l);
      if (lane(t.top, l) == 0) rebase(t, s, m, l);
      return;
    }
  }
  if (cnt == s.cap / 2) purge(t, s, m, l);
}

// Settles a candidate (sorted point sp, id pid, size lam > 0, key u / lam) at lane l (the scalar twin of the vector
// path in offer_lanes): a key below the lane's threshold joins its buffer and its histogram.
inline void settle(Tile& t, const LaneScratch& s, int m, int l, int sp, int pid, double lam, double key) {
  if (!(key < lane(t.thr, l))) return;
  int64_t& cnt = lane(t.cnt, l);
  lane_entries(s, l)[cnt++] = LaneEntry{key, lam, pid, sp};
  if (lane(t.top, l) >= 0) {
    const int b = window_bin(lane(t.base, l), key);
    ++lane_hist(s, l)[b];
    lane(t.low, l) = b < lane(t.low, l) ? b : lane(t.low, l);
    lane(t.below, l) += b < lane(t.top, l);
  }
  fix_lane(t, s, m, l);
}

// Lane l's exact sample: moves its m smallest entries (by (key, id)) to the front and returns xi_(m+1) (+inf when
// the lane has at most m entries, i.e. every point with lambda > 0 it met).
inline double select_sample(Tile& t, const LaneScratch& s, int m, int l) {
  if (lane(t.top, l) < 0) return INFINITY;
  if (lane(t.below, l) > m) lower_threshold(t, s, m, l);
  LaneEntry* e = lane_entries(s, l);
  LaneEntry* tmp = e + s.cap / 2;  // the buffer's second half (entries fill at most the first)
  const int64_t base = lane(t.base, l), top = lane(t.top, l);
  int below = 0, at = 0;
  for (int i = 0; i < lane(t.cnt, l); ++i) {  // bins below `top` in place, the threshold bin aside, the rest dropped
    const int b = window_bin(base, e[i].key);
    e[below] = e[i];
    tmp[at] = e[i];
    below += b < top;
    at += b == top;
  }
  std::sort(tmp, tmp + at, [](const LaneEntry& a, const LaneEntry& b) { return key_less(a.key, a.id, b.key, b.id); });
  for (int i = 0; below + i <= m; ++i) e[below + i] = tmp[i];
  lane(t.cnt, l) = m;
  return e[m].key;
}

inline double lane_uniform(const Tile& t, const LaneJob& job, int l, int s, int pid, uint32_t hi) {
  if (job.strat_base) return shifted_uniform(job.strat_base[s], lane(t.shift, l));
  return uniform_of(hi, draw_lo(static_cast<uint64_t>(reinterpret_cast<const uint32_t*>(t.b)[l]) << 32,
                                static_cast<uint32_t>(pid)));
}

// Offers sorted point sp to every active lane. Candidates (u may lie below xi_(m+1) lambda, tested on the high
// hash) get their exact key u / lambda for the whole vector (the bits of uniform_of and of the scalar division);
// those below their lane's threshold are appended to the lanes' buffers and histograms by masked scatters, the
// same operations as settle's lane by lane; the rare follow-ups (fix_lane) run per lane.
inline void offer_lanes(Tile& t, const LaneJob& job, const LaneScratch& s, int sp) {
  const TreeView& T = job.tree;
  const double mx = T.mu[2 * sp], my = T.mu[2 * sp + 1];
  const double ca = T.con[3 * sp], cb = 2.0 * T.con[3 * sp + 1], cc = T.con[3 * sp + 2], la = T.logA[sp];
  const int pid = T.id[sp];
  const VU hi_key = bcast_u(static_cast<uint32_t>(pid) * 0x9E3779B9u);
  const VU lo_key = bcast_u(static_cast<uint32_t>(pid) * 0x85EBCA6Bu);
  VL payload;  // the entry's third word: id, sorted index
  for (int j = 0; j < kW; ++j) payload[j] = static_cast<int64_t>(static_cast<uint32_t>(pid)) |
                                            static_cast<int64_t>(static_cast<uint64_t>(static_cast<uint32_t>(sp)) << 32);
  const int m = job.m;
  uint32_t fix = 0;
  for (int c = 0; c < kC; ++c) {
    if (!((t.active >> (c * kW)) & ((1u << kW) - 1))) continue;  // no lane of this vector is searching
    const VD dx = t.U[c] - mx, dy = t.V[c] - my;
    const VD q = vfma(ca * dx, dx, vfma(cb * dx, dy, cc * dy * dy));
    const VD lam = lane_exp(vmin(vfma(q, bcast(-0.5), bcast(la)), bcast(kLogAlphaMax)));
    const VL act = t.act[c];
    t.vis[c] += act ? lam : bcast(0.0);
    t.evals[c] -= act;
    const VD bound = t.thr[c] * lam * kBoundMargin;
    VD u;
    VL cand;
    if (job.strat_base) {
      u = job.strat_base[sp] + t.shift[c];
      u = u >= 1.0 ? u - 1.0 : u;
      u = u > 0.0 ? u : bcast(5.551115123125783e-17);
      cand = act & (lam > 0.0) & (u < bound);
      if (!movemask(cand)) continue;
    } else {
      const VU hi = lane_hash(t.a[c] + hi_key);
      cand = act & (lam > 0.0) & (__builtin_convertvector(hi, VD) * 0x1p-32 < bound);
      if (!movemask(cand)) continue;
      const VU lo = lane_hash(t.b[c] ^ lo_key);
      u = __builtin_convertvector(hi, VD) * 0x1p-32 + (__builtin_convertvector(lo >> 11, VD) + 0.5) * 0x1p-53;
    }
    const VD key = u / lam;
    const VL in = cand & (key < t.thr[c]);
    if (!movemask(in)) continue;
    const VL slot = (t.lane_id[c] * s.cap + t.cnt[c]) * 3;  // LaneEntry = 3 words: key, lam, (id, sorted)
    scatter_d(reinterpret_cast<double*>(s.entries), slot, key, in);
    scatter_d(reinterpret_cast<double*>(s.entries), slot + 1, lam, in);
    scatter_q(reinterpret_cast<int64_t*>(s.entries), slot + 2, payload, in);
    t.cnt[c] -= in;
    const VL steady = in & (t.top[c] >= 0);
    if (movemask(steady)) {
      VL bin = reinterpret_cast<VL>(reinterpret_cast<VQ>(key) >> kHistShift) - t.base[c];
      bin = bin < 0 ? VL{} : bin;
      const VL hidx = t.lane_id[c] * kHistBins + bin;
      scatter_h(s.hist, hidx, gather_h(s.hist, hidx, steady) + 1, steady);
      t.low[c] = steady & (bin < t.low[c]) ? bin : t.low[c];
      t.below[c] -= steady & (bin < t.top[c]);
    }
    const VL after = in & ((t.top[c] < 0 ? t.cnt[c] == m + 1 : (t.below[c] > m + kWalkSlack) | (t.cnt[c] == s.cap / 2)));
    fix |= movemask(after) << (c * kW);
  }
  for (; fix; fix &= fix - 1) fix_lane(t, s, m, __builtin_ctz(fix));
}

// The scalar twin of offer_lanes for lane l (far subtrees).
inline void offer_lane(Tile& t, const LaneJob& job, const LaneScratch& s, int sp, int l) {
  const TreeView& T = job.tree;
  const double u0 = lane(t.U, l), v0 = lane(t.V, l);
  const double dx = u0 - T.mu[2 * sp], dy = v0 - T.mu[2 * sp + 1];
  const double q = std::fma(T.con[3 * sp] * dx, dx, std::fma(2.0 * T.con[3 * sp + 1] * dx, dy, T.con[3 * sp + 2] * dy * dy));
  const double t0 = std::fma(q, -0.5, T.logA[sp]);
  const double lam = lane_exp1(t0 < kLogAlphaMax ? t0 : kLogAlphaMax);
  lane(t.vis, l) += lam;
  reinterpret_cast<int64_t*>(t.evals)[l] += 1;
  if (!(lam > 0.0)) return;
  const int pid = T.id[sp];
  const uint32_t hi = draw_hi(static_cast<uint64_t>(reinterpret_cast<const uint32_t*>(t.a)[l]),
                              static_cast<uint32_t>(pid));
  const double u = lane_uniform(t, job, l, sp, pid, hi);
  if (u < lane(t.thr, l) * lam * kBoundMargin) settle(t, s, job.m, l, sp, pid, lam, u / lam);
}

// Depth-first search of far subtree `root` for lane l (sps.h: search_subtree): a node is pruned when the lane's
// (P + U_n) xi_(m+1) < eps kDfsShare.
inline void subtree_lane(Tile& t, const LaneJob& job, const LaneScratch& s, int root, int l) {
  const TreeView& T = job.tree;
  const double u0 = lane(t.U, l), v0 = lane(t.V, l), limit = job.eps * kDfsShare;
  int node_st[kStackSize];
  double lub_st[kStackSize], est_st[kStackSize];
  int sp = 0;
  ensure_hermite(T, job.hermite, root);
  node_bound(T, root, u0, v0, &lub_st[0], &est_st[0]);
  node_st[sp++] = root;
  while (sp > 0) {
    --sp;
    const int node = node_st[sp];
    const double rest = lane(t.thr, l);
    if (rest < INFINITY) {
      const double ub = dmax(bound_exp1(lub_st[sp]) * kBoundMargin, kBoundFloor);
      const double p = lane(t.pru, l) + ub;
      if (p * rest * kBoundMargin < limit) {
        lane(t.pru, l) = p;
        lane(t.est, l) += est_st[sp];
        continue;
      }
    }
    const InternalNode& nd = T.nodes[node];
    if (nd.last - nd.first + 1 <= kLeafSize) {
      for (int q = nd.first; q <= nd.last; ++q) offer_lane(t, job, s, q, l);
      continue;
    }
    const int child[2] = {nd.left, nd.right};
    double cl[2], ce[2];
    for (int c = 0; c < 2; ++c) {
      if (child[c] < 0) {
        offer_lane(t, job, s, ~child[c], l);
        cl[c] = -INFINITY;
      } else {
        ensure_hermite(T, job.hermite, child[c]);
        node_bound(T, child[c], u0, v0, &cl[c], &ce[c]);
      }
    }
    const int first = cl[0] <= cl[1] ? 0 : 1;  // push the smaller bound first: the larger is visited next
    for (int o = 0; o < 2; ++o) {
      const int c = o == 0 ? first : 1 - first;
      if (child[c] < 0) continue;
      node_st[sp] = child[c];
      lub_st[sp] = cl[c];
      est_st[sp] = ce[c];
      ++sp;
    }
  }
}

// Per-lane log bound of an item (tile.h: item_log_bound).
inline VD item_bound(const TileItem& it, VD u, VD v) {
  const VD dx = u - it.g.cx, dy = v - it.g.cy;
  const VD q = it.g.ma * dx * dx + 2.0 * it.g.mb * dx * dy + it.g.mc * dy * dy;
  const VD d = vsqrt(vmax(q, bcast(0.0))) - it.g.r;
  const VD bx = vmax(vmax(it.box[0] - u, u - it.box[2]), bcast(0.0));
  const VD by = vmax(vmax(it.box[1] - v, v - it.box[3]), bcast(0.0));
  const VD e = d > 0.0 ? 0.5 * d * d : bcast(0.0);
  return it.log_amp - vmax(e, (bx * bx + by * by) * it.inv2h2);
}

// Pixel l's output from its exact sample (the first cnt entries of its buffer, threshold `rest`): inclusion
// probabilities (kThreshold: min(1, lambda xi_(m+1)); kPips: min(1, c lambda) with sum pi = m, c from the sampled
// lambdas and Lambda_hat; 1 when the sample holds every point with lambda > 0, xi_(m+1) = inf), then the slots
// front to back by per-pixel depth, ties by id (rank of each entry among the others).
inline void finish_lane(const LaneJob& job, const Tile& t, const LaneScratch& s, int l, int cnt, double rest,
                        double total) {
  const int m = job.m;
  LaneEntry* e = lane_entries(s, l);
  int* out_id = s.out_id + static_cast<int64_t>(l) * m;
  double* out_pi = s.out_pi + static_cast<int64_t>(l) * m;
  double c = INFINITY;
  const bool certain = rest == INFINITY;
  if (job.inclusion == kPips && cnt == m && !certain) {
    double* lam = out_pi;  // scratch: the sampled lambdas, descending
    for (int i = 0; i < cnt; ++i) lam[i] = e[i].lam;
    std::sort(lam, lam + cnt, [](double a, double b) { return a > b; });
    double rest_mass = total;
    for (int j = 0; j < cnt; ++j) {
      const double cj = (m - j) / rest_mass;
      if (cj * lam[j] < 1.0) {
        c = cj;
        break;
      }
      rest_mass -= lam[j];
      if (rest_mass <= 1e-12 * total) break;  // the remaining mass is rounding noise: all certainty units
    }
  }
  const Ray ray = pixel_ray(job.K, lane(t.U, l), lane(t.V, l));
  alignas(64) double depth[kMaxRankSort], ids[kMaxRankSort];
  const bool rank = cnt <= kMaxRankSort;
  for (int i = 0; i < cnt; ++i) {
    const int sp = e[i].sorted;
    bool on_plane;
    double dot;
    const double d = splat_depth(job.nrm + 3 * sp, job.off[sp], job.zc[sp], ray, &on_plane, &dot);
    const double pi = certain ? 1.0 : job.inclusion == kPips ? (c == INFINITY ? 1.0 : c * e[i].lam) : e[i].lam * rest;
    e[i].lam = dmin(1.0, pi);  // the entry now carries its inclusion probability
    e[i].key = d;              // and its depth
    if (rank) {
      depth[i] = d;
      ids[i] = e[i].id;
    }
  }
  if (!rank) {
    std::sort(e, e + cnt, [](const LaneEntry& a, const LaneEntry& b) { return key_less(a.key, a.id, b.key, b.id); });
    for (int i = 0; i < cnt; ++i) {
      out_id[i] = e[i].id;
      out_pi[i] = e[i].lam;
    }
    return;
  }
  for (int i = cnt; i < (cnt + kW - 1) / kW * kW; ++i) {
    depth[i] = INFINITY;  // padding sorts last
    ids[i] = 2147483647.0;
  }
  // rank of each entry by depth; equal depths (rare) share a rank and are then ordered by id
  uint64_t used[kMaxRankSort / 64] = {0};
  bool ties = false;
  for (int i = 0; i < cnt; ++i) {
    const VD di = bcast(depth[i]);
    int r = 0;
    for (int j = 0; j < cnt; j += kW) {
      VD dj;
      std::memcpy(&dj, depth + j, sizeof dj);
      r += __builtin_popcount(movemask(dj < di));
    }
    ties |= (used[r >> 6] >> (r & 63)) & 1;
    used[r >> 6] |= uint64_t(1) << (r & 63);
    out_id[r] = i;
  }
  if (ties) {
    for (int i = 0; i < cnt; ++i) {
      int r = 0;
      for (int j = 0; j < cnt; ++j) r += depth[j] < depth[i] || (depth[j] == depth[i] && ids[j] < ids[i]);
      out_id[r] = i;
    }
  }
  for (int r = 0; r < cnt; ++r) {  // out_id holds entry indices by rank: replace them by ids and probabilities
    const LaneEntry& en = e[out_id[r]];
    out_id[r] = en.id;
    out_pi[r] = en.lam;
  }
}

}  // namespace

void NS_LANE_SEARCH(const LaneJob& job, const TileItem* items, int n, int64_t x0, int64_t y0, int w, int h,
                    const LaneScratch& s, LaneResult* out) {
  Tile t;
  uint32_t in_image = 0;
  for (int l = 0; l < kLanes; ++l) {
    const int col = l % kTileSize, row = l / kTileSize;
    lane(t.U, l) = static_cast<double>(x0 + col) + 0.5;
    lane(t.V, l) = static_cast<double>(y0 + row) + 0.5;
    const bool inside = col < w && row < h;
    in_image |= static_cast<uint32_t>(inside) << l;
    const int64_t p = inside ? (y0 + row) * job.width + x0 + col : 0;
    const Draw d = pixel_draw(job.seed, job.camera, p, job.width, job.strat_base != nullptr);
    reinterpret_cast<uint32_t*>(t.a)[l] = static_cast<uint32_t>(d.stream);
    reinterpret_cast<uint32_t*>(t.b)[l] = static_cast<uint32_t>(d.stream >> 32);
    lane(t.shift, l) = d.shift;
    lane(t.lane_id, l) = l;
    lane(t.cnt, l) = 0;
    lane(t.top, l) = -1;
    lane(t.below, l) = 0;
    lane(t.base, l) = 0;
    lane(t.low, l) = kHistBins;
  }
  for (int c = 0; c < kC; ++c) {
    t.thr[c] = bcast(INFINITY);
    t.vis[c] = t.pru[c] = t.est[c] = bcast(0.0);
    t.evals[c] = VL{};
    t.act[c] = lane_mask(in_image, c);
  }
  t.active = in_image;

  // Per-lane linear bounds of the items (far ones: their bound over the tile), and the visit order: by bin of
  // the largest bound (near items before far ones within a bin, each in item order).
  int count[2 * kBins + 1];
  for (int b = 0; b <= 2 * kBins; ++b) count[b] = 0;
  for (int i = 0; i < n; ++i) {
    double* bi = s.bound + static_cast<int64_t>(i) * kLanes;
    int key;
    if (items[i].tile_bin < 0) {
      double top = -INFINITY;
      for (int c = 0; c < kC; ++c) {
        const VD lb = item_bound(items[i], t.U[c], t.V[c]);
        const VD ub = vmax(bound_exp(lb) * kBoundMargin, bcast(kBoundFloor));
        std::memcpy(bi + c * kW, &ub, sizeof ub);
        const VD masked = t.act[c] ? lb : bcast(-INFINITY);
        for (int j = 0; j < kW; ++j) top = dmax(top, masked[j]);
      }
      key = 2 * bound_bin(top);
    } else {
      const TileItem& it = items[i];
      const double lt = item_rect_log_bound(it, static_cast<double>(x0) + 0.5, static_cast<double>(y0) + 0.5,
                                            static_cast<double>(x0 + w) - 0.5, static_cast<double>(y0 + h) - 0.5);
      const double ub = dmax(bound_exp1(lt) * kBoundMargin, kBoundFloor);
      for (int l = 0; l < kLanes; ++l) bi[l] = ub;
      key = 2 * it.tile_bin + 1;
    }
    s.order[i] = key;  // the bucket for now
    ++count[key + 1];
  }
  for (int b = 0; b < 2 * kBins; ++b) count[b + 1] += count[b];
  // place item indices by bucket, reusing suffix's first n ints... simpler: a second pass into s.order
  {
    int* pos = reinterpret_cast<int*>(s.suffix);  // n ints of scratch (suffix has >= n doubles)
    for (int i = 0; i < n; ++i) pos[count[s.order[i]]++] = i;
    for (int i = 0; i < n; ++i) s.order[i] = pos[i];
  }
  // suffix[k] = sum of the bounds of visit positions k.. (exact sums of upper bounds, margin in kBoundMargin);
  // scratch arrays are not vector aligned: loads and stores go through memcpy
  const double grow = 1.0 + 4.5e-16 * n;
  double* suf = s.suffix;
  for (int l = 0; l < kLanes; ++l) suf[static_cast<int64_t>(n) * kLanes + l] = 0.0;
  for (int k = n - 1; k >= 0; --k) {
    const double* bi = s.bound + static_cast<int64_t>(s.order[k]) * kLanes;
    double* sk = suf + static_cast<int64_t>(k) * kLanes;
    for (int c = 0; c < kC; ++c) {
      VD b, next;
      std::memcpy(&b, bi + c * kW, sizeof b);
      std::memcpy(&next, sk + kLanes + c * kW, sizeof next);
      next += b;
      std::memcpy(sk + c * kW, &next, sizeof next);
    }
  }

  for (int k = 0; k < n && t.active; ++k) {
    VD R[kC];
    for (int c = 0; c < kC; ++c) {
      std::memcpy(&R[c], suf + static_cast<int64_t>(k) * kLanes + c * kW, sizeof R[c]);
      R[c] *= grow;
    }
    uint32_t stop = 0;
    for (int c = 0; c < kC; ++c) {
      const VD P = t.pru[c];
      const VL st =
          t.act[c] & (((t.vis[c] + P + R[c]) < kMinTotal) | ((P + R[c]) * t.thr[c] * kBoundMargin < job.eps));
      t.pru[c] = st ? P + R[c] : P;
      t.est[c] = st ? t.est[c] + 0.5 * R[c] : t.est[c];
      t.act[c] &= ~st;
      stop |= movemask(st) << (c * kW);
    }
    t.active &= ~stop;
    if (!t.active) break;
    const TileItem& it = items[s.order[k]];
    if (it.group) {
      for (int sp = it.first; sp <= it.last; ++sp) offer_lanes(t, job, s, sp);
    } else {
      for (uint32_t a = t.active; a; a &= a - 1) subtree_lane(t, job, s, it.ref, __builtin_ctz(a));
    }
  }
  for (int l = 0; l < kLanes; ++l) {
    if (!((in_image >> l) & 1)) continue;
    const double rest = select_sample(t, s, job.m, l);
    clear_hist(t, s, l);
    const double total = lane(t.vis, l) + lane(t.est, l);
    const int cnt = total < kMinTotal ? 0 : static_cast<int>(lane(t.cnt, l) < job.m ? lane(t.cnt, l) : job.m);
    finish_lane(job, t, s, l, cnt, rest, total);
    out[l].total = total < kMinTotal ? 0.0 : total;
    out[l].cnt = cnt;
    out[l].evaluated = static_cast<int>(reinterpret_cast<const int64_t*>(t.evals)[l]);
  }
}

}  // namespace nsplat
