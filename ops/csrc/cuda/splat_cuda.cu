// CUDA backend: kernels calling the same core headers as the CPU backend (ops/csrc/cpu/splat_cpu.cpp).
//
// Same four entry points with the same semantics as the CPU module (declared and checked in bindings.cpp):
//   sample_cuda                     the parallel tree build (Karras 2012) of every camera of the call at once,
//                                   one launch per step (CudaTrees); then per camera group (up to
//                                   kCameraGroup = 16 cameras, so all of most calls' cameras: one launch
//                                   per phase for the group, the cameras' trees and streams in a kernel
//                                   argument, CameraGroup): tile item lists (one thread per (camera, tile,
//                                   slot), then one sort into the pixel pass's layout; one read of sizes back
//                                   to the host per call, whatever the cameras), then one or more threads per
//                                   pixel (lanes, tile.h) over the group's (camera, tile) in chunks, a tile's
//                                   pixels on consecutive threads, each with its heap interleaved with its
//                                   neighbours' (PixelPass); with several lanes a merge over (pixel, lane)
//                                   threads, each lane's entries placed at their ranks among the pixel's
//                                   lanes, then one thread per pixel
//   composite_forward_cuda          one thread per (camera, pixel)
//   composite_backward_pixels_cuda  pass 1, one thread per (camera, pixel)
//   composite_backward_points_cuda  pass 2, one thread per point over its entries sorted by (point, camera)
// Every loop of the CPU backend maps to a kernel whose threads run the CPU loop body unchanged, so both
// backends draw identical samples and agree up to floating-point rounding (FMA contraction, libm vs CUDA
// math). No atomics in the outputs: results are deterministic run to run.
//
// Memory: the per-pixel heaps live in global memory (per camera of a group, L heaps of (double, int) entries of
// pixels x samples for L lanes per pixel; with several lanes their LaneStats and one merged heap), so `samples` is
// limited by memory only; a group holds as many cameras as keep this scratch within kLaneScratchBytes (one at
// least). All slot offsets are 64-bit. The cameras' trees of a call are alive together, each sized for all N points
// of the call (its valid count stays on the device): 216 bytes per point and camera with the bound metrics and keys;
// the tile items of a camera group take sizeof(TileItem) (120 B) each, twice while they are
// arranged; the near items' per-pixel bins one byte per (item, tile pixel), at most kBinScratchBytes per sampling
// launch (a launch's tiles may span the group's cameras).
//
// Only the CUDA runtime/cub headers and torch's ATen + c10/cuda headers are needed here (not ATen/cuda, which
// pulls in cuBLAS/cuSPARSE headers): the Python binding lives in bindings.cpp, and this file compiles to an
// object with a bare CUDA toolkit and a CPU-only torch wheel (.ci/cuda_compile_check.sh).
//
// With NSPLAT_CUDA_EMULATE defined (emulate.cpp), the same file compiles with the host compiler: kernels run
// sequentially over their grid on the CPU (emulate.h), cub's sort/scan are replaced by std ones (launch.h). Tests use
// that build to check the launch code against the CPU backend bit for bit on machines without a GPU.
#include "launch.h"

#include <cstdlib>

#include "../core/composite.h"
#include "../core/sps.h"
#include "../core/tile.h"
#include "../core/tree_build.h"

namespace nsplat {
namespace {

constexpr int kPixelThreads = 128;  // block size of the per-pixel traversal / compositing kernels
// Registers of a sample_kernel thread (launched with kPixelThreads): the search and, with one lane, the pixel's
// finalisation inlined into it need about 167; under __launch_bounds__(kPixelThreads) ptxas capped them at 128 and
// spilled 384 bytes (.ci/cuda_compile_check.sh checks stack and spills per kernel).
constexpr int kSampleRegisters = 168;
constexpr int kReduceBlocks = 256;  // first-stage blocks of the bounding-box reduction
constexpr int kFeatChunk = 8;       // channels accumulated in registers at once in pass 2
// Per-pixel item bins of one sampling launch; a build may lower it (the host-emulation tests use 4 KiB, so
// that their scenes take several launches, some of a single tile larger than the limit).
#ifndef NSPLAT_BIN_SCRATCH_BYTES
#define NSPLAT_BIN_SCRATCH_BYTES (int64_t(256) << 20)
#endif
constexpr int64_t kBinScratchBytes = NSPLAT_BIN_SCRATCH_BYTES;
// Threads per pixel of the sampler (tile.h, "Lanes"): the largest power of two up to kMaxPixelLanes that keeps
// pixels x lanes <= kLaneThreads (about one H100's resident threads) and the lanes' heaps within
// kLaneScratchBytes. NSPLAT_CUDA_PIXEL_LANES=<k> sets it (tests, timing).
constexpr int kMaxPixelLanes = 16;
constexpr int64_t kLaneThreads = int64_t(1) << 18;
constexpr int64_t kLaneScratchBytes = int64_t(1) << 30;

// A positive integer setting from the environment, else `fallback`: NSPLAT_CUDA_SORT_CAMERAS (cameras of one key sort)
// and NSPLAT_CUDA_LANE_SCRATCH_BYTES (kLaneScratchBytes) let tests on a GPU take several key sorts and camera groups.
int64_t env_setting(const char* name, int64_t fallback) {
  const char* env = std::getenv(name);
  if (env == nullptr) return fallback;
  const long long value = std::atoll(env);
  TORCH_CHECK(value >= 1, name, " must be a positive integer, got '", env, "'");
  return value;
}

// The CPU builder's std::min / std::max (NaN never replaces the running value).
__device__ __forceinline__ double cpu_min(double cur, double x) { return x < cur ? x : cur; }
__device__ __forceinline__ double cpu_max(double cur, double x) { return cur < x ? x : cur; }

// ---------------------------------------------------------------------------------------------------------
// Tree build kernels, for all cameras of a call at once (CudaTrees). Points with amp > 0 are "valid" (the CPU
// builder's filter). The splats are [B, N, ...]: camera b's point k at b N + k.

// Stage 1 of the box of each camera's valid means: blocks b parts .. (b + 1) parts - 1 take camera b, each thread a
// partial (lox, loy, hix, hiy) and valid count over a stride of the camera's points (no shared memory or barriers:
// the partials are few, parts x kThreads per camera), at part_box / part_cnt[b parts kThreads + thread].
template <typename S>
__global__ void box_partial_kernel(const S* __restrict__ mu, const S* __restrict__ amp, int64_t N, int64_t parts,
                                   double* __restrict__ part_box, int64_t* __restrict__ part_cnt) {
  const int64_t b = blockIdx.x / parts, threads = parts * blockDim.x;
  const int64_t t = (blockIdx.x % parts) * blockDim.x + threadIdx.x;
  double lox = INFINITY, loy = INFINITY, hix = -INFINITY, hiy = -INFINITY;
  int64_t cnt = 0;
  for (int64_t k = b * N + t; k < (b + 1) * N; k += threads) {
    if (!(amp[k] > S(0))) continue;
    const double x = static_cast<double>(mu[2 * k]), y = static_cast<double>(mu[2 * k + 1]);
    lox = cpu_min(lox, x);
    hix = cpu_max(hix, x);
    loy = cpu_min(loy, y);
    hiy = cpu_max(hiy, y);
    ++cnt;
  }
  const int64_t o = b * threads + t;
  part_box[4 * o] = lox;
  part_box[4 * o + 1] = loy;
  part_box[4 * o + 2] = hix;
  part_box[4 * o + 3] = hiy;
  part_cnt[o] = cnt;
}

// Stages 2 and 3, per camera b < B: thread (b, c, j), c < 5, folds component c (4: the count) of camera b's partials
// j, j + folds, ... (of `parts` per camera) into its fold j; folds = 1 gives each camera's box and count. Min/max and
// integer sums: the result does not depend on the grouping.
__global__ void box_fold_kernel(const double* __restrict__ part_box, const int64_t* __restrict__ part_cnt, int64_t B,
                                int64_t parts, int64_t folds, double* __restrict__ out_box,
                                int64_t* __restrict__ out_cnt) {
  NS_GRID_STRIDE(t, B * 5 * folds) {
    const int64_t b = t / (5 * folds), c = (t / folds) % 5, j = t % folds;
    const double* box = part_box + 4 * b * parts;
    const int64_t* cnts = part_cnt + b * parts;
    if (c < 4) {
      double acc = c < 2 ? INFINITY : -INFINITY;
      for (int64_t i = j; i < parts; i += folds)
        acc = c < 2 ? cpu_min(acc, box[4 * i + c]) : cpu_max(acc, box[4 * i + c]);
      out_box[4 * (b * folds + j) + c] = acc;
    } else {
      int64_t cnt = 0;
      for (int64_t i = j; i < parts; i += folds) cnt += cnts[i];
      out_cnt[b * folds + j] = cnt;
    }
  }
}

// The sort keys of cameras [b0, b0 + cams), packed so that one radix sort over `cam_bits` + 32 + `nb` bits orders
// them by camera, then by morton_key (the CPU builder's key: a 32-bit code above the point's index): camera
// b0 + c's point k gets c << (32 + nb) | code << nb | k with k < 2^nb - 1, an invalid point the all-ones code and
// index, which sort after the camera's valid keys.
template <typename S>
__global__ void morton_kernel(const S* __restrict__ mu, const S* __restrict__ amp, const S* __restrict__ sig2,
                              int64_t N, int64_t b0, int64_t cams, int nb, const double* __restrict__ box,
                              uint64_t* __restrict__ keys) {
  NS_GRID_STRIDE(g, cams * N) {
    const int64_t c = g / N, b = b0 + c, k = b * N + g % N;
    const double* bx = box + 4 * b;
    const double ex = bx[2] - bx[0], ey = bx[3] - bx[1];
    const double ext = ex < ey ? ey : ex;  // std::max(ex, ey), as on the CPU
    const double inv_ext = ext > 0 ? 1.0 / ext : 0.0;
    const uint64_t low = amp[k] > S(0)
                             ? (morton_key(static_cast<double>(mu[2 * k]), static_cast<double>(mu[2 * k + 1]),
                                           static_cast<double>(sig2[k]), bx[0], bx[1], inv_ext, g % N) >> 32
                                << nb) | static_cast<uint64_t>(g % N)
                             : (uint64_t(1) << (32 + nb)) - 1;
    keys[g] = static_cast<uint64_t>(c) << (32 + nb) | low;
  }
}

// The sorted packed keys of cameras [b0, b0 + cams) back in morton_key's form (~0 for invalid points): each camera
// has N of them, so its sorted keys land at b N.
__global__ void unpack_keys_kernel(const uint64_t* __restrict__ packed, int64_t N, int64_t b0, int64_t cams, int nb,
                                   uint64_t* __restrict__ keys) {
  NS_GRID_STRIDE(g, cams * N) {
    const uint64_t index_mask = (uint64_t(1) << nb) - 1, p = packed[g];
    const uint64_t k = p & index_mask, code = (p >> nb) & 0xFFFFFFFFull;
    keys[b0 * N + g] = k == index_mask ? ~0ull : code << 32 | k;
  }
}

// Kernels of phases 2 and 3 run one thread per (camera b, element) over blocks of `stride` elements (stride = N, the
// bound of every camera's valid count); camera b's valid count n = count[b] (on the device, never read by the host)
// says which of its block are live.

// Camera b's sorted points' double copies (the CPU builder's second loop), leaf s at b stride + s.
template <typename S>
__global__ void gather_kernel(const uint64_t* __restrict__ keys, const int64_t* __restrict__ count, int64_t B,
                              int64_t N, int64_t stride, const S* __restrict__ mu, const S* __restrict__ con,
                              const S* __restrict__ amp, const S* __restrict__ sig2, int* __restrict__ id,
                              double* __restrict__ tmu, double* __restrict__ tcon, double* __restrict__ tamp,
                              double* __restrict__ tlogA, double* __restrict__ tsig2) {
  NS_GRID_STRIDE(g, B * stride) {
    const int64_t b = g / stride, s = g % stride;
    if (s >= count[b]) continue;
    const int64_t local = static_cast<int64_t>(keys[b * N + s] & 0xFFFFFFFFull), k = b * N + local;
    id[g] = static_cast<int>(local);
    tmu[2 * g] = static_cast<double>(mu[2 * k]);
    tmu[2 * g + 1] = static_cast<double>(mu[2 * k + 1]);
    for (int c = 0; c < 3; ++c) tcon[3 * g + c] = static_cast<double>(con[3 * k + c]);
    tamp[g] = static_cast<double>(amp[k]);
    tlogA[g] = log(tamp[g]);
    tsig2[g] = static_cast<double>(sig2[k]);
  }
}

// Internal node i of camera b (blocks of ni = stride - 1 nodes).
__global__ void internal_nodes_kernel(const uint64_t* __restrict__ keys, const int64_t* __restrict__ count, int64_t B,
                                      int64_t N, int64_t stride, InternalNode* nodes, int* parent_int,
                                      int* parent_leaf) {
  const int64_t ni = stride - 1;
  NS_GRID_STRIDE(g, B * ni) {
    const int64_t b = g / ni, i = g % ni, n = count[b];
    if (i < n - 1) build_internal_node(keys + b * N, n, i, nodes + b * ni, parent_int + b * ni, parent_leaf + b * stride);
  }
}

// Bottom-up aggregates: one thread per leaf; the second arrival at a node computes it (tree_build.h).
// `agg` is read and written by different threads: it must not be read through the read-only cache.
__global__ void propagate_kernel(const int64_t* __restrict__ count, int64_t B, int64_t stride,
                                 const InternalNode* nodes, const int* parent_int, const int* parent_leaf,
                                 const double* mu, const double* amp, const double* sig2, NodeAgg* agg, int* flags) {
  const int64_t ni = stride - 1;
  NS_GRID_STRIDE(g, B * stride) {
    const int64_t b = g / stride, s = g % stride, n = count[b];
    if (n < 2 || s >= n) continue;
    propagate_up(s, nodes + b * ni, parent_int + b * ni, parent_leaf + b * stride, mu + 2 * b * stride,
                 amp + b * stride, sig2 + b * stride, agg + b * ni, flags + b * ni);
  }
}

// Expansion order per node; also writes p^2 into sq[g] (zero for dead nodes) for the offsets' exclusive scan.
__global__ void choose_expansion_kernel(const int64_t* __restrict__ count, int64_t B, int64_t stride,
                                        const InternalNode* __restrict__ nodes, const NodeAgg* __restrict__ agg,
                                        double tol, int pmax, int* __restrict__ p, double* __restrict__ err,
                                        int64_t* __restrict__ sq) {
  const int64_t ni = stride - 1;
  NS_GRID_STRIDE(g, B * ni) {
    const int64_t b = g / ni, i = g % ni;
    if (i >= count[b] - 1) continue;
    choose_expansion(i, nodes + b * ni, agg + b * ni, tol, pmax, p + g, err + g);
    sq[g] = static_cast<int64_t>(p[g]) * p[g];
  }
}

// herm_off holds the offsets of all cameras' nodes into the one coefficient array `coef`.
__global__ void coefficients_kernel(const int64_t* __restrict__ count, int64_t B, int64_t stride,
                                    const InternalNode* __restrict__ nodes, const NodeAgg* __restrict__ agg,
                                    const int* __restrict__ p, const int64_t* __restrict__ off,
                                    const double* __restrict__ mu, const double* __restrict__ amp,
                                    double* __restrict__ coef) {
  const int64_t ni = stride - 1;
  NS_GRID_STRIDE(g, B * ni) {
    const int64_t b = g / ni, i = g % ni;
    if (i >= count[b] - 1) continue;
    expansion_coefficients(i, nodes + b * ni, agg + b * ni, p + b * ni, off + b * ni, mu + 2 * b * stride,
                           amp + b * stride, coef);
  }
}

// Cameras of one key sort: at most NSPLAT_SORT_CAMERAS (a build may lower it: the host-emulation tests use 4, so
// that their calls take several sorts), as many as keep the packed keys within 64 bits and the sort within cub's
// int item count.
#ifndef NSPLAT_SORT_CAMERAS
#define NSPLAT_SORT_CAMERAS (int64_t(1) << 20)
#endif

// Bits of the values 0 .. v.
inline int bit_length(int64_t v) {
  int bits = 0;
  while (bits < 63 && (int64_t(1) << bits) <= v) ++bits;
  return bits;
}

// The trees of a call's B cameras, built together in three phases, so that a call reads sizes back to the host once
// in all (sample_cuda: the coefficient total with the tile item offsets) and each step of the CPU builder is one
// kernel (or cub primitive) for every camera, not one per camera. The valid counts stay on the device (T.count): every
// camera's block is sized for the bound N, its sorted keys at b N, its leaves at b stride, its internal nodes at
// b (stride - 1), stride = max(N, 1); the kernels skip the elements past camera b's count. Dead nodes take no
// coefficients (p^2 = 0), so the coefficient offsets herm_off, one exclusive scan over all the cameras' nodes, are
// those of the compact layout and index the call's one coefficient array herm_coef.
struct CudaTrees {
  int64_t B = 0, N = 0, stride = 1;
  at::Tensor keys, count, nodes, agg, herm_p, herm_off, herm_err, herm_coef, mu, con, logA, amp, sig2, id;

  int64_t inner() const { return stride - 1; }

  template <typename T>
  static T* ptr(const at::Tensor& t, int64_t at) {
    return t.defined() && t.numel() ? reinterpret_cast<T*>(t.data_ptr()) + at : nullptr;
  }

  // Camera b's tree (no bound metrics) but for its valid count, which is on the device: n is left at -1, and the
  // kernels take it from CameraGroup::tree. The arrays are those of N points (null when the call has none).
  TreeView view(int64_t b) const {
    TreeView t{};
    t.n = -1;
    t.mu = ptr<const double>(mu, 2 * b * stride);
    t.con = ptr<const double>(con, 3 * b * stride);
    t.logA = ptr<const double>(logA, b * stride);
    t.sig2 = ptr<const double>(sig2, b * stride);
    t.id = ptr<const int>(id, b * stride);
    t.nodes = ptr<const InternalNode>(nodes, b * inner());
    t.agg = ptr<const NodeAgg>(agg, b * inner());
    t.herm_p = ptr<const int>(herm_p, b * inner());
    t.herm_off = ptr<const int64_t>(herm_off, b * inner());
    t.herm_err = ptr<const double>(herm_err, b * inner());
    t.herm_coef = ptr<const double>(herm_coef, 0);
    t.metric = nullptr;
    return t;
  }
};

// Phase 1: each camera's box and count of valid means (the counts into T.count, on the device), the Morton keys and
// their radix sort, NSPLAT_SORT_CAMERAS cameras a sort.
template <typename S>
void tree_keys(CudaTrees& T, const S* mu, const S* amp, const S* sig2, int64_t B, int64_t N,
               const at::TensorOptions& dev, Stream stream) {
  const auto dbl = dev.dtype(at::kDouble);
  const auto i64 = dev.dtype(at::kLong);
  T.B = B;
  T.N = N;
  T.count = at::zeros({B}, i64);
  if (N == 0) return;
  const int64_t parts = std::min<int64_t>(kReduceBlocks, blocks_for(N, kThreads));
  at::Tensor part_box = at::empty({B * parts * kThreads, 4}, dbl), part_cnt = at::empty({B * parts * kThreads}, i64);
  NS_LAUNCH(box_partial_kernel<S>, static_cast<unsigned int>(B * parts), kThreads, stream, mu, amp, N, parts,
            part_box.data_ptr<double>(), part_cnt.data_ptr<int64_t>());
  NS_LAUNCH_CHECK();
  at::Tensor mid_box = at::empty({B * kThreads, 4}, dbl), mid_cnt = at::empty({B * kThreads}, i64);
  NS_LAUNCH(box_fold_kernel, blocks_for(B * 5 * kThreads, kThreads), kThreads, stream, part_box.data_ptr<double>(),
            part_cnt.data_ptr<int64_t>(), B, parts * kThreads, kThreads, mid_box.data_ptr<double>(),
            mid_cnt.data_ptr<int64_t>());
  NS_LAUNCH_CHECK();
  at::Tensor box = at::empty({B, 4}, dbl);
  NS_LAUNCH(box_fold_kernel, blocks_for(B * 5, kThreads), kThreads, stream, mid_box.data_ptr<double>(),
            mid_cnt.data_ptr<int64_t>(), B, kThreads, 1, box.data_ptr<double>(), T.count.data_ptr<int64_t>());
  NS_LAUNCH_CHECK();
  // packed keys (morton_kernel) need 32 + nb bits plus the camera's bits
  const int nb = bit_length(N);
  const int64_t per_sort = std::max<int64_t>(
      1, std::min<int64_t>({B, env_setting("NSPLAT_CUDA_SORT_CAMERAS", NSPLAT_SORT_CAMERAS), int64_t(1) << (32 - nb),
                            int64_t(INT32_MAX) / N}));
  at::Tensor raw = at::empty({2, per_sort * N}, i64);
  T.keys = at::empty({B * N}, i64);
  for (int64_t b0 = 0; b0 < B; b0 += per_sort) {
    const int64_t cams = std::min(per_sort, B - b0);
    NS_LAUNCH(morton_kernel<S>, blocks_for(cams * N, kThreads), kThreads, stream, mu, amp, sig2, N, b0, cams, nb,
              box.data_ptr<double>(), as<uint64_t>(raw));
    NS_LAUNCH_CHECK();
    sort_keys(as<uint64_t>(raw), as<uint64_t>(raw) + raw.size(1), cams * N, bit_length(cams - 1) + 32 + nb, dev,
              stream);
    NS_LAUNCH(unpack_keys_kernel, blocks_for(cams * N, kThreads), kThreads, stream, as<uint64_t>(raw) + raw.size(1), N,
              b0, cams, nb, as<uint64_t>(T.keys));
    NS_LAUNCH_CHECK();
  }
}

// Phase 2, with the valid counts on the device (blocks of the bound N points a camera): sorted double copies,
// internal nodes, bottom-up aggregates, expansion orders and the coefficient offsets (their total stays on the
// device, at T.herm_off[B (stride - 1)]).
template <typename S>
void tree_nodes(CudaTrees& T, const S* mu, const S* con, const S* amp, const S* sig2, int order, double tol,
                const at::TensorOptions& dev, Stream stream) {
  T.stride = std::max<int64_t>(1, T.N);
  if (T.N == 0) return;
  const int64_t B = T.B, L = B * T.stride, I = B * T.inner();
  const auto dbl = dev.dtype(at::kDouble);
  const auto i64 = dev.dtype(at::kLong);
  const auto i32 = dev.dtype(at::kInt);
  const uint64_t* keys = as<uint64_t>(T.keys);
  const int64_t* count = T.count.data_ptr<int64_t>();
  T.id = at::empty({L}, i32);
  T.mu = at::empty({L, 2}, dbl);
  T.con = at::empty({L, 3}, dbl);
  T.amp = at::empty({L}, dbl);
  T.logA = at::empty({L}, dbl);
  T.sig2 = at::empty({L}, dbl);
  NS_LAUNCH(gather_kernel<S>, blocks_for(L, kThreads), kThreads, stream, keys, count, B, T.N, T.stride, mu, con, amp,
            sig2, T.id.data_ptr<int>(), T.mu.data_ptr<double>(), T.con.data_ptr<double>(), T.amp.data_ptr<double>(),
            T.logA.data_ptr<double>(), T.sig2.data_ptr<double>());
  NS_LAUNCH_CHECK();
  if (I == 0) return;
  T.nodes = bytes(I * static_cast<int64_t>(sizeof(InternalNode)), dev);
  T.agg = bytes(I * static_cast<int64_t>(sizeof(NodeAgg)), dev);
  at::Tensor parent_int = at::full({I}, -1, i32), parent_leaf = at::full({L}, -1, i32);
  at::Tensor flags = at::zeros({I}, i32);
  NS_LAUNCH(internal_nodes_kernel, blocks_for(I, kThreads), kThreads, stream, keys, count, B, T.N, T.stride,
            as<InternalNode>(T.nodes), parent_int.data_ptr<int>(), parent_leaf.data_ptr<int>());
  NS_LAUNCH_CHECK();
  NS_LAUNCH(propagate_kernel, blocks_for(L, kThreads), kThreads, stream, count, B, T.stride, as<InternalNode>(T.nodes),
            parent_int.data_ptr<int>(), parent_leaf.data_ptr<int>(), T.mu.data_ptr<double>(), T.amp.data_ptr<double>(),
            T.sig2.data_ptr<double>(), as<NodeAgg>(T.agg), flags.data_ptr<int>());
  NS_LAUNCH_CHECK();
  T.herm_p = at::empty({I}, i32);
  T.herm_err = at::empty({I}, dbl);
  at::Tensor sq = at::zeros({I + 1}, i64);  // p^2 per node, one trailing zero: the scan's last entry is the total
  NS_LAUNCH(choose_expansion_kernel, blocks_for(I, kThreads), kThreads, stream, count, B, T.stride,
            as<InternalNode>(T.nodes), as<NodeAgg>(T.agg), tol, order, T.herm_p.data_ptr<int>(),
            T.herm_err.data_ptr<double>(), sq.data_ptr<int64_t>());
  NS_LAUNCH_CHECK();
  T.herm_off = at::empty({I + 1}, i64);
  exclusive_sum(sq.data_ptr<int64_t>(), T.herm_off.data_ptr<int64_t>(), I + 1, dev, stream);
}

// Phase 3, with the coefficient total known on the host: the expansion coefficients of every camera's nodes.
inline void tree_coefficients(CudaTrees& T, int64_t total, const at::TensorOptions& dev, Stream stream) {
  const int64_t I = T.B * T.inner();
  if (I == 0) return;
  T.herm_coef = at::zeros({std::max<int64_t>(total, 1)}, dev.dtype(at::kDouble));
  NS_LAUNCH(coefficients_kernel, blocks_for(I, kThreads), kThreads, stream, T.count.data_ptr<int64_t>(), T.B, T.stride,
            as<InternalNode>(T.nodes), as<NodeAgg>(T.agg), T.herm_p.data_ptr<int>(), T.herm_off.data_ptr<int64_t>(),
            T.mu.data_ptr<double>(), T.amp.data_ptr<double>(), T.herm_coef.data_ptr<double>());
  NS_LAUNCH_CHECK();
}

// Device-side copy of the projected-splat base pointers of all cameras ([B, N, ...] layouts).
template <typename S>
struct SplatsBase {
  const S *mu, *con, *amp, *nrm, *off, *zc;
  int64_t N;

  __host__ __device__ SplatsView<S> camera(int64_t b) const {
    SplatsView<S> v;
    v.mu = mu + b * N * 2;
    v.con = con + b * N * 3;
    v.amp = amp + b * N;
    v.nrm = nrm + b * N * 3;
    v.off = off + b * N;
    v.zc = zc + b * N;
    return v;
  }
};

template <typename S>
SplatsBase<S> splats_base(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp, const at::Tensor& nrm,
                          const at::Tensor& off, const at::Tensor& zc) {
  return SplatsBase<S>{mu.data_ptr<S>(), con.data_ptr<S>(), amp.data_ptr<S>(), nrm.data_ptr<S>(),
                       off.data_ptr<S>(), zc.data_ptr<S>(), amp.size(1)};
}

// ---------------------------------------------------------------------------------------------------------
// Per-pixel kernels.

// The cameras of one launch of the tile and pixel passes (at most kCameraGroup of them, cameras first ..
// first + count - 1 of the call): their trees and (seed, camera) streams, passed by value as a kernel argument,
// so that no per-camera table is copied to the device. Camera c of the group is camera first + c of the call. The
// trees' valid counts are on the device (n_valid[first + c], CudaTrees::count; tv[c].n is unset): tree(c) is camera
// c's tree with its count.
constexpr int kCameraGroup = 16;
struct CameraGroup {
  int64_t first, count;
  const int64_t* n_valid;  // [B] the call's valid counts, on the device
  TreeView tv[kCameraGroup];
  uint64_t seed[kCameraGroup];
  int64_t camera[kCameraGroup];

  __device__ __forceinline__ TreeView tree(int64_t c) const {
    TreeView t = tv[c];
    t.n = n_valid[first + c];
    return t;
  }
};

// Bound metrics of the group nodes (tile.h), one thread per (camera, internal node): camera c's metrics at
// metric[c stride + i] (stride >= its internal nodes; the grid covers the bound, threads past the camera's nodes
// exit).
__global__ void group_metric_kernel(CameraGroup cg, int64_t stride, ItemMetric* __restrict__ metric) {
  NS_GRID_STRIDE(g, cg.count * stride) {
    const int64_t c = g / stride, i = g % stride;
    const TreeView tv = cg.tree(c);
    if (i >= tv.n - 1) continue;
    const InternalNode& nd = tv.nodes[i];
    if (nd.last - nd.first + 1 <= kGroupSize) metric[c * stride + i] = group_metric(tv, nd.first, nd.last);
  }
}

// The tile pass's image: its size, tiles and thresholds.
struct TileGrid {
  int64_t width, height, tiles_x, tiles;
  double log_theta, log_far;
};

// The rectangle spanned by the pixel centres of tile t.
struct TileRect {
  double x0, y0, x1, y1;
};

__device__ __forceinline__ TileRect tile_rect(const TileGrid& grid, int64_t t) {
  const int64_t x0 = (t % grid.tiles_x) * kTileSize, y0 = (t / grid.tiles_x) * kTileSize;
  const int64_t x1 = x0 + kTileSize < grid.width ? x0 + kTileSize : grid.width;
  const int64_t y1 = y0 + kTileSize < grid.height ? y0 + kTileSize : grid.height;
  return TileRect{x0 + 0.5, y0 + 0.5, x1 - 0.5, y1 - 0.5};
}

// Arrangement class of a tile item: 0 near, 1 + tile_bin far. Sorting a camera group's items stably by (camera tile,
// class) gives every tile's list in arrange_tile_items' layout.
constexpr int kItemClasses = kBins + 1;

// Tile item lists (tile.h) of a camera group, one thread per (camera tile, slot) (tile.h, "Slots"), camera tile
// T = c tiles + t for tile t of camera c: first each slot's item count (raw == nullptr); then, at the counts'
// exclusive scan slot_off, the slots' items into `raw` (tile_items' lists, camera tile after camera tile), each with
// its key T kItemClasses + class into `keys` and its position into `pos`.
__global__ void slot_items_kernel(CameraGroup cg, TileGrid grid, int64_t* __restrict__ counts,
                                  const int64_t* __restrict__ slot_off, TileItem* __restrict__ raw,
                                  uint64_t* __restrict__ keys, int* __restrict__ pos) {
  NS_GRID_STRIDE(g, cg.count * grid.tiles * kTileSlots) {
    const int64_t T = g / kTileSlots, c = T / grid.tiles, t = T % grid.tiles;
    const int slot = static_cast<int>(g % kTileSlots);
    const TileRect r = tile_rect(grid, t);
    const TreeView tv = cg.tree(c);
    if (!raw) {
      counts[g] = tile_slot_items(tv, slot, r.x0, r.y0, r.x1, r.y1, grid.log_theta, grid.log_far, nullptr);
      continue;
    }
    const int64_t o = slot_off[g];
    const int n = tile_slot_items(tv, slot, r.x0, r.y0, r.x1, r.y1, grid.log_theta, grid.log_far, raw + o);
    for (int i = 0; i < n; ++i) {
      keys[o + i] = static_cast<uint64_t>(T) * kItemClasses + static_cast<uint64_t>(raw[o + i].tile_bin + 1);
      pos[o + i] = static_cast<int>(o + i);
    }
  }
}

// Each (camera) tile's item offset, that of its first slot (entry `tiles`: the total).
__global__ void tile_offsets_kernel(const int64_t* __restrict__ slot_off, int64_t tiles, int64_t* __restrict__ offsets) {
  NS_GRID_STRIDE(t, tiles + 1) offsets[t] = slot_off[t * kTileSlots];
}

// The items in arrange_tile_items' layout, from their stable sort by key: item i is raw[pos[i]]; a tile's last near
// item writes the tile's near count (near_counts is zeroed).
__global__ void arrange_items_kernel(const TileItem* __restrict__ raw, const uint64_t* __restrict__ keys,
                                     const int* __restrict__ pos, int64_t n, const int64_t* __restrict__ offsets,
                                     TileItem* __restrict__ items, int* __restrict__ near_counts) {
  NS_GRID_STRIDE(i, n) {
    items[i] = raw[pos[i]];
    const uint64_t k = keys[i];
    if (k % kItemClasses == 0 && (i + 1 == n || keys[i + 1] != k)) {
      const int64_t t = static_cast<int64_t>(k / kItemClasses);
      near_counts[t] = static_cast<int>(i + 1 - offsets[t]);
    }
  }
}

// Bits of the arrangement keys of `tiles` (camera) tiles.
inline int item_key_bits(int64_t tiles) {
  int bits = 1;
  while ((int64_t(1) << bits) < tiles * kItemClasses) ++bits;
  return bits;
}

constexpr int kTilePixels = kTileSize * kTileSize;

// The pixel pass of a camera group (sample_kernel, then the merge kernels with several lanes): its cameras' trees and
// streams, the call's splats, intrinsics and outputs ([B, pixels, ...]), and the group's tile lists over its camera
// tiles T = c tiles + t (items of T at items[offsets[T]..offsets[T + 1]), near_counts[T]). `log_eps` is the log of a
// lane's budget eps / lanes. The heaps interleave (sps.h): heap h's entry j at key[j * heaps + h] and
// heap_idx[j * heaps + h], heap h = (T lanes + lane) kTilePixels + l for lane `lane` of pixel l of camera tile T, so
// that consecutive threads of the pixel kernels access consecutive entries. With several lanes, lane_stats[h] holds
// each lane's LaneStats and merged_key / merged_idx the merged heaps, pixel l of camera tile T at entry
// j * merged + T kTilePixels + l.
template <typename S>
struct PixelPass {
  CameraGroup cg;
  SplatsBase<S> base;
  const double* K;  // [B, 3, 3]
  int64_t width, height, tiles_x, tiles;
  int m, lanes, inclusion;
  double log_eps;
  bool stratified;
  const TileItem* items;
  const int64_t* offsets;
  const int* near_counts;
  uint8_t* bin8;
  double* key;
  int* heap_idx;
  int64_t heaps;
  LaneStats* lane_stats;
  double* merged_key;
  int* merged_idx;
  double* merged_rest;
  int64_t merged;
  int* idx;  // [B, pixels, m] outputs
  S* prob;
  S* total;  // [B, pixels]
  int* work;
};
// Within the 4 KiB of kernel arguments of every CUDA version.
static_assert(sizeof(PixelPass<double>) <= 4096, "PixelPass exceeds the kernel argument space");

// Camera tile T of a pixel pass: its camera c in the group, the camera's index b in the call and its tile t.
struct CameraTile {
  int64_t c, b, t;
};

template <typename S>
__device__ __forceinline__ CameraTile camera_tile(const PixelPass<S>& pp, int64_t T) {
  const int64_t c = T / pp.tiles;
  return CameraTile{c, pp.cg.first + c, T % pp.tiles};
}

// Pixel l (< kTilePixels) of tile t: its coordinates and whether it lies inside the image.
struct TilePixel {
  int64_t px, py, p;
  bool inside;
};

template <typename S>
__device__ __forceinline__ TilePixel tile_pixel(const PixelPass<S>& pp, int64_t t, int l) {
  TilePixel q;
  q.px = (t % pp.tiles_x) * kTileSize + l % kTileSize;
  q.py = (t / pp.tiles_x) * kTileSize + l / kTileSize;
  q.inside = q.px < pp.width && q.py < pp.height;
  q.p = q.py * pp.width + q.px;
  return q;
}

// Thread g of the pixel kernels over camera tiles from T0 (sample_kernel's layout): its camera tile T, heap h, and
// its lane and pixel l of the tile.
struct LaneThread {
  int64_t T, h;
  CameraTile ct;
  int lane, l;
  TilePixel q;
};

template <typename S>
__device__ __forceinline__ LaneThread lane_thread(const PixelPass<S>& pp, int64_t T0, int64_t g) {
  const int64_t per_tile = static_cast<int64_t>(pp.lanes) * kTilePixels;
  LaneThread th;
  th.T = T0 + g / per_tile;
  th.h = T0 * per_tile + g;
  th.ct = camera_tile(pp, th.T);
  th.lane = static_cast<int>((g / kTilePixels) % pp.lanes);
  th.l = static_cast<int>(g % kTilePixels);
  th.q = tile_pixel(pp, th.ct.t, th.l);
  return th;
}

// The search of thread th's lane of its pixel into its heap (tile.h, sample_lane), stopped early below `floor`.
template <typename S>
__device__ __forceinline__ LaneStats search_lane(const PixelPass<S>& pp, const LaneThread& th, int64_t T0,
                                                 double floor) {
  const double u = static_cast<double>(th.q.px) + 0.5, v = static_cast<double>(th.q.py) + 0.5;
  const Draw draw = pixel_draw(pp.cg.seed[th.ct.c], pp.cg.camera[th.ct.c], th.q.p, pp.width, pp.stratified);
  const int n = static_cast<int>(pp.offsets[th.T + 1] - pp.offsets[th.T]);
  uint8_t* bins = pp.bin8 + (pp.offsets[th.T] - pp.offsets[T0]) * kTilePixels + th.l;
  return sample_lane(pp.cg.tree(th.ct.c), pp.items + pp.offsets[th.T], n, pp.near_counts[th.T], u, v, draw, pp.m,
                     pp.log_eps, floor, th.lane, pp.lanes, pp.key + th.h, pp.heap_idx + th.h, pp.heaps, bins,
                     kTilePixels);
}

// Sampling of a camera group over its camera tiles [T0, T1), `lanes` threads per pixel (tile.h, "Lanes"): thread
// g takes camera tile T0 + g / (lanes kTilePixels), lane (g / kTilePixels) % lanes and pixel g % kTilePixels of the
// tile, so that the 16 threads of a (tile, lane) read the same items (idle past the image's edge), and heap
// h = T0 lanes kTilePixels + g. Near-item bins go to `bin8`, the tile's pixels' bytes interleaved: item i of camera
// tile T, pixel l at bin8[(offsets[T] - offsets[T0] + i) * kTilePixels + l] (item i belongs to lane i % lanes: each
// byte has one writer). With one lane the pixel is finished here; with several each lane leaves its heap and its
// LaneStats for the merge kernels.
template <typename S>
__global__ void __maxnreg__(kSampleRegisters)
    sample_kernel(PixelPass<S> pp, int64_t T0, int64_t T1) {
  const int m = pp.m, lanes = pp.lanes;
  const int64_t P = pp.width * pp.height;
  NS_GRID_STRIDE(g, (T1 - T0) * lanes * kTilePixels) {
    const LaneThread th = lane_thread(pp, T0, g);
    if (!th.q.inside) continue;
    if (lanes > 1) {
      pp.lane_stats[th.h] = search_lane(pp, th, T0, kMinTotal / lanes);
      continue;
    }
    const LaneStats ls = search_lane(pp, th, T0, kMinTotal);
    const double u = static_cast<double>(th.q.px) + 0.5, v = static_cast<double>(th.q.py) + 0.5;
    const Ray ray = pixel_ray(pp.K + th.ct.b * 9, u, v);
    const int64_t o = th.ct.b * P + th.q.p;
    finalize_pixel(pp.base.camera(th.ct.b), u, v, ray, m, ls.cnt, ls.px.total, ls.px.rest,
                   ls.px.exhaustive && ls.px.evaluated == ls.cnt, pp.inclusion, pp.key + th.h, pp.heap_idx + th.h,
                   pp.heaps, pp.idx + o * m, pp.prob + o * m);
    pp.total[o] = static_cast<S>(ls.px.total < kMinTotal ? 0.0 : ls.px.total);
    pp.work[o] = ls.px.evaluated;
  }
}

// The merge of the lanes' heaps into each pixel's sample (tile.h, "Lanes") over camera tiles [T0, T1), in three
// kernels:
// merge_prepare_kernel and merge_rank_kernel with sample_kernel's threads (one per pixel and lane), then
// merge_finish_kernel with one thread per pixel. A pixel whose lanes' bounds sum below kMinTotal stays empty;
// otherwise every lane stopped by its floor test searches again without it, and the lanes' sorted heaps merge by
// (key, id) into the m smallest, xi_(m+1) being the smallest key left (the (m+1)-th smallest heap entry or a
// lane's own threshold).

// Sum of the bounds of the lanes of the pixel whose lane 0 has heap h0 (in lane order).
__device__ __forceinline__ double lanes_bound(const LaneStats* ls, int64_t h0, int lanes) {
  double bound = 0.0;
  for (int j = 0; j < lanes; ++j) bound += ls[h0 + j * kTilePixels].bound;
  return bound;
}

// Each lane of a pixel that is not certified below the floor: searches again without the floor test if its floor
// test stopped it, then sorts its heap; each lane of a certified pixel: an empty heap (cnt = 0). A lane rewrites
// only the px and cnt of its own LaneStats: the pixel's other lanes read their bounds meanwhile.
template <typename S>
__global__ void __launch_bounds__(kPixelThreads)
    merge_prepare_kernel(PixelPass<S> pp, int64_t T0, int64_t T1) {
  const int64_t per_tile = static_cast<int64_t>(pp.lanes) * kTilePixels;
  NS_GRID_STRIDE(g, (T1 - T0) * per_tile) {
    const LaneThread th = lane_thread(pp, T0, g);
    if (!th.q.inside) continue;
    LaneStats& ls = pp.lane_stats[th.h];
    if (lanes_bound(pp.lane_stats, th.T * per_tile + th.l, pp.lanes) < kMinTotal) {
      ls.cnt = 0;
      continue;
    }
    if (ls.floored) {
      const LaneStats again = search_lane(pp, th, T0, 0.0);
      ls.px = again.px;
      ls.cnt = again.cnt;
    }
    heap_sort(pp.key + th.h, pp.heap_idx + th.h, pp.heaps, ls.cnt);
  }
}

// Entries of the sorted heap h (cnt entries) before (k, id) in (key, id) order.
__host__ __device__ __forceinline__ int entries_before(const double* key, const int* idx, int64_t stride, int cnt, double k,
                                              int id) {
  int lo = 0, hi = cnt;
  while (lo < hi) {
    const int mid = (lo + hi) / 2;
    if (key_less(key[mid * stride], idx[mid * stride], k, id)) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

// Each entry i of the sorted heap of lane `lane` goes to its rank in the pixel's merged order, i plus the entries of
// the other lanes' heaps before it (the points' ids are distinct, so the ranks are too): ranks below m into the
// merged heap (entry r at merged_key[r * HM], merged_idx[r * HM]), rank m, the smallest key left, into
// *merged_rest. Lane j's heap is h0 + j kTilePixels (entry i at key[i * H + h0 + j kTilePixels]), its size
// stats[h0 + j kTilePixels].cnt.
__host__ __device__ __forceinline__ void rank_lane(const double* key, const int* idx, int64_t H, const LaneStats* stats,
                                                   int64_t h0, int lane, int lanes, int m, double* merged_key,
                                                   int* merged_idx, int64_t HM, double* merged_rest) {
  const int64_t h = h0 + lane * kTilePixels;
  for (int i = 0; i < stats[h].cnt; ++i) {
    const double k = key[i * H + h];
    const int id = idx[i * H + h];
    int rank = i;
    for (int j = 0; j < lanes; ++j) {
      const int64_t hj = h0 + j * kTilePixels;
      if (j != lane) rank += entries_before(key + hj, idx + hj, H, stats[hj].cnt, k, id);
    }
    if (rank > m) break;  // the ranks grow with i
    if (rank == m) {
      *merged_rest = k;
    } else {
      merged_key[rank * HM] = k;
      merged_idx[rank * HM] = id;
    }
  }
}

// rank_lane for each lane of each pixel of camera tiles [T0, T1), with sample_kernel's threads.
template <typename S>
__global__ void __launch_bounds__(kPixelThreads)
    merge_rank_kernel(PixelPass<S> pp, int64_t T0, int64_t T1) {
  const int64_t per_tile = static_cast<int64_t>(pp.lanes) * kTilePixels;
  NS_GRID_STRIDE(g, (T1 - T0) * per_tile) {
    const LaneThread th = lane_thread(pp, T0, g);
    if (!th.q.inside) continue;
    const int64_t hm = th.T * kTilePixels + th.l;
    rank_lane(pp.key, pp.heap_idx, pp.heaps, pp.lane_stats, th.T * per_tile + th.l, th.lane, pp.lanes, pp.m,
              pp.merged_key + hm, pp.merged_idx + hm, pp.merged, pp.merged_rest + hm);
  }
}

// Each pixel's sample from its merged heap and its lanes' stats (summed in lane order).
template <typename S>
__global__ void __launch_bounds__(kPixelThreads)
    merge_finish_kernel(PixelPass<S> pp, int64_t T0, int64_t T1) {
  const int m = pp.m, lanes = pp.lanes;
  const int64_t per_tile = static_cast<int64_t>(lanes) * kTilePixels, P = pp.width * pp.height;
  NS_GRID_STRIDE(g, (T1 - T0) * kTilePixels) {
    const int64_t T = T0 + g / kTilePixels;
    const CameraTile ct = camera_tile(pp, T);
    const int l = static_cast<int>(g % kTilePixels);
    const TilePixel q = tile_pixel(pp, ct.t, l);
    if (!q.inside) continue;
    const int64_t h0 = T * per_tile + l, hm = T * kTilePixels + l;
    const LaneStats* ls = pp.lane_stats;
    const bool empty = lanes_bound(ls, h0, lanes) < kMinTotal;
    int entries = 0, evaluated = 0;
    double total = 0.0, rest = INFINITY;
    bool exhaustive = true;
    for (int j = 0; j < lanes; ++j) {
      const LaneStats& lj = ls[h0 + j * kTilePixels];
      evaluated += lj.px.evaluated;
      if (empty) continue;
      entries += lj.cnt;
      total += lj.px.total;
      exhaustive = exhaustive && lj.px.exhaustive;
      rest = dmin(rest, lj.px.rest);
    }
    if (entries > m) rest = dmin(rest, pp.merged_rest[hm]);
    const int cnt = entries < m ? entries : m;
    const double u = static_cast<double>(q.px) + 0.5, v = static_cast<double>(q.py) + 0.5;
    const Ray ray = pixel_ray(pp.K + ct.b * 9, u, v);
    const int64_t o = ct.b * P + q.p;
    finalize_pixel(pp.base.camera(ct.b), u, v, ray, m, cnt, total, rest, exhaustive && evaluated == cnt, pp.inclusion,
                   pp.merged_key + hm, pp.merged_idx + hm, pp.merged, pp.idx + o * m, pp.prob + o * m);
    pp.total[o] = static_cast<S>(total < kMinTotal ? 0.0 : total);
    pp.work[o] = evaluated;
  }
}

template <typename S>
__global__ void __launch_bounds__(kPixelThreads)
    composite_forward_kernel(SplatsBase<S> base, const double* __restrict__ Kd, const S* __restrict__ feat, int C,
                             int64_t feat_stride, const S* __restrict__ bg, const int* __restrict__ indices, const S* __restrict__ probs,
                             int m, int64_t W, int64_t P, int64_t BP, int mode, S* __restrict__ image,
                             S* __restrict__ alpha, S* __restrict__ depth) {
  NS_GRID_STRIDE(o, BP) {
    const int64_t b = o / P, p = o % P;
    const double u = static_cast<double>(p % W) + 0.5, v = static_cast<double>(p / W) + 0.5;
    const Ray ray = pixel_ray(Kd + b * 9, u, v);
    composite_pixel(base.camera(b), feat + b * feat_stride, C, bg, indices + o * m, probs + o * m, m, S(u), S(v), ray, mode,
                    image + o * C, alpha + o, depth + o);
  }
}

template <typename S>
__global__ void __launch_bounds__(kPixelThreads)
    backward_pixels_kernel(SplatsBase<S> base, const double* __restrict__ Kd, const S* __restrict__ feat, int C,
                           int64_t feat_stride, const S* __restrict__ bg, const int* __restrict__ indices, const S* __restrict__ probs,
                           int m, int64_t W, int64_t P, int64_t BP, int mode, int estimator,
                           const S* __restrict__ g_img, const S* __restrict__ g_alpha, const S* __restrict__ g_depth,
                           S* __restrict__ dalpha, S* __restrict__ wf, S* __restrict__ bgw) {
  NS_GRID_STRIDE(o, BP) {
    const int64_t b = o / P, p = o % P;
    const double u = static_cast<double>(p % W) + 0.5, v = static_cast<double>(p / W) + 0.5;
    const Ray ray = pixel_ray(Kd + b * 9, u, v);
    bgw[o] = composite_backward_pixel(base.camera(b), feat + b * feat_stride, C, bg, indices + o * m, probs + o * m, m, S(u), S(v), ray,
                                      mode, estimator, g_img + o * C, g_alpha[o], g_depth[o], dalpha + o * m,
                                      wf + o * m);
  }
}

// Output pointers of pass 2.
template <typename S>
struct PointGrads {
  S *mu, *con, *amp, *nrm, *off, *zc, *feat;
};

// Pass 2: one thread per point k over its entries (flat slot ids sorted by (point, camera), segment
// seg[k]..seg[k+1]); per camera segment the CPU loop body, with the feature gradient accumulated in
// register chunks of kFeatChunk channels (same summation order per channel as the CPU).
template <typename S>
__global__ void __launch_bounds__(kPixelThreads)
    backward_points_kernel(SplatsBase<S> base, const double* __restrict__ Kd, const int64_t* __restrict__ ent,
                           const int64_t* __restrict__ sg, const S* __restrict__ da, const S* __restrict__ w,
                           const S* __restrict__ gi, const S* __restrict__ gd, int64_t m, int64_t C, int64_t width,
                           int64_t P, bool paper, bool per_camera, PointGrads<S> out) {
  const int64_t N = base.N, Pm = P * m;
  NS_GRID_STRIDE(k, N) {
    int64_t e = sg[k];
    const int64_t end = sg[k + 1];
    while (e < end) {
      const int64_t b = ent[e] / Pm;
      const SplatsView<S> sv = base.camera(b);
      const double* K = Kd + b * 9;
      S a_mu[2] = {0, 0}, a_con[3] = {0, 0, 0}, a_amp = 0, a_nrm[3] = {0, 0, 0}, a_off = 0, a_zc = 0;
      S gf[kFeatChunk];
#pragma unroll
      for (int c = 0; c < kFeatChunk; ++c) gf[c] = S(0);
      const int64_t e0 = e;
      int64_t count = 0;
      for (; e < end && ent[e] / Pm == b; ++e, ++count) {
        const int64_t flat = ent[e];
        const int64_t pix = (flat / m) % P;
        const int64_t o = b * P + pix;
        const double u = static_cast<double>(pix % width) + 0.5, v = static_cast<double>(pix / width) + 0.5;
        const Ray ray = pixel_ray(K, u, v);
#pragma unroll
        for (int c = 0; c < kFeatChunk; ++c)
          if (c < C) gf[c] += w[flat] * gi[o * C + c];
        splat_grad_entry(sv, static_cast<int>(k), S(u), S(v), ray, da[flat], w[flat] * gd[o], a_mu, a_con, &a_amp,
                         a_nrm, &a_off, &a_zc);
      }
      const int64_t e1 = e;
      const S scale = paper ? S(1) / S(count) : S(1);
      const int64_t bk = b * N + k;
      S* feat_out = out.feat + (per_camera ? bk : k) * C;  // [B,N,C] features: camera b's own row
      for (int c = 0; c < 2; ++c) out.mu[bk * 2 + c] = a_mu[c] * scale;
      for (int c = 0; c < 3; ++c) out.con[bk * 3 + c] = a_con[c] * scale;
      for (int c = 0; c < 3; ++c) out.nrm[bk * 3 + c] = a_nrm[c] * scale;
      out.amp[bk] = a_amp * scale;
      out.off[bk] = a_off * scale;
      out.zc[bk] = a_zc * scale;
#pragma unroll
      for (int c = 0; c < kFeatChunk; ++c)
        if (c < C) feat_out[c] += gf[c] * scale;
      // Remaining channels, kFeatChunk at a time, over the same entries.
      for (int64_t c0 = kFeatChunk; c0 < C; c0 += kFeatChunk) {
#pragma unroll
        for (int c = 0; c < kFeatChunk; ++c) gf[c] = S(0);
        for (int64_t f = e0; f < e1; ++f) {
          const int64_t flat = ent[f];
          const int64_t o = b * P + (flat / m) % P;
#pragma unroll
          for (int c = 0; c < kFeatChunk; ++c)
            if (c0 + c < C) gf[c] += w[flat] * gi[o * C + c0 + c];
        }
#pragma unroll
        for (int c = 0; c < kFeatChunk; ++c)
          if (c0 + c < C) feat_out[c0 + c] += gf[c] * scale;
      }
    }
  }
}

// Threads per pixel for a P-pixel image and sample size m (see kMaxPixelLanes).
int pixel_lanes(int64_t P, int64_t m) {
  if (const char* env = std::getenv("NSPLAT_CUDA_PIXEL_LANES")) {
    const int k = std::atoi(env);
    TORCH_CHECK(k >= 1 && k <= kMaxPixelLanes, "NSPLAT_CUDA_PIXEL_LANES must be an integer in [1, ", kMaxPixelLanes,
                "], got '", env, "'");
    return k;
  }
  const int64_t per_lane = std::max<int64_t>(P, 1) * (m * 12 + static_cast<int64_t>(sizeof(LaneStats)));
  int k = 1;
  const int64_t scratch = env_setting("NSPLAT_CUDA_LANE_SCRATCH_BYTES", kLaneScratchBytes);
  while (2 * k <= kMaxPixelLanes && 2 * k * P <= kLaneThreads && 2 * k * per_lane <= scratch) k *= 2;
  return k;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Entry points (argument checks in bindings.cpp).

std::vector<at::Tensor> sample_cuda(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp,
                                    const at::Tensor& sig2, const at::Tensor& nrm, const at::Tensor& off,
                                    const at::Tensor& zc, const at::Tensor& Ks, const at::Tensor& streams,
                                    int64_t width, int64_t height, int64_t samples, double eps, int64_t order,
                                    double tol, int64_t inclusion, bool stratified) {
  const DeviceGuard guard(mu.device());
  const Stream stream = current_stream();
  const int64_t B = amp.size(0), N = amp.size(1), P = width * height, m = samples;
  auto opts = mu.options();
  at::Tensor indices = at::empty({B, height, width, samples}, opts.dtype(at::kInt));
  at::Tensor probs = at::empty({B, height, width, samples}, opts);
  at::Tensor total = at::empty({B, height, width, 1}, opts);
  at::Tensor work = at::empty({B, height, width, 1}, opts.dtype(at::kInt));
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  if (P == 0 || B == 0) return {indices, probs, total, work};
  const int lanes = pixel_lanes(P, m);
  const int64_t tiles_x = (width + kTileSize - 1) / kTileSize, tiles = tiles_x * ((height + kTileSize - 1) / kTileSize);
  // Camera groups: at most kCameraGroup cameras each, and as many as keep their per-pixel scratch within
  // kLaneScratchBytes (one camera at least): one heap per lane and tile pixel, interleaved (PixelPass); with several
  // lanes their LaneStats and the merged heaps. The scratch is sized for a full group and reused by every group.
  const int64_t camera_scratch =
      tiles * kTilePixels *
      (lanes * m * 12 + (lanes > 1 ? lanes * static_cast<int64_t>(sizeof(LaneStats)) + m * 12 + 8 : 0));
  const int64_t scratch = env_setting("NSPLAT_CUDA_LANE_SCRATCH_BYTES", kLaneScratchBytes);
  const int64_t group = std::max<int64_t>(1, std::min<int64_t>({B, kCameraGroup, scratch / std::max<int64_t>(camera_scratch, 1)}));
  const int64_t groups = (B + group - 1) / group;
  const int64_t heaps = group * tiles * lanes * kTilePixels, merged = group * tiles * kTilePixels;
  at::Tensor key_scratch = at::empty({heaps * m}, opts.dtype(at::kDouble));
  at::Tensor heap_idx = at::empty({heaps * m}, opts.dtype(at::kInt));
  at::Tensor lane_stats, merged_key, merged_idx, merged_rest;
  if (lanes > 1) {
    lane_stats = bytes(heaps * static_cast<int64_t>(sizeof(LaneStats)), opts);
    merged_key = at::empty({merged * m}, opts.dtype(at::kDouble));
    merged_idx = at::empty({merged * m}, opts.dtype(at::kInt));
    merged_rest = at::empty({merged}, opts.dtype(at::kDouble));
  }
  const double log_eps = std::log(eps), lane_log_eps = std::log(eps / lanes);
  const double log_theta = tile_log_theta(log_eps, static_cast<int>(m)), log_far = tile_log_far(log_eps, static_cast<int>(m));
  const int64_t* st = streams.data_ptr<int64_t>();  // (seed, camera) of each camera, on the host
  const auto i64 = opts.dtype(at::kLong);
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_sample_cuda", [&] {
    using S = scalar_t;
    const SplatsBase<S> base = splats_base<S>(mu, con, amp, nrm, off, zc);
    // Every camera's tree and tile lists, with one read of sizes back to the host for the whole call, `sizes`: per
    // group g (cameras g group ..), the item offsets of its camera tiles (group tiles + 1 entries from
    // g (group tiles + 1)), then the trees' coefficient total (entry B tiles + groups). The trees' valid counts stay
    // on the device: the trees and the bound metrics are sized for N points a camera.
    CudaTrees trees;
    tree_keys<S>(trees, mu.data_ptr<S>(), amp.data_ptr<S>(), sig2.data_ptr<S>(), B, N, opts, stream);
    tree_nodes<S>(trees, mu.data_ptr<S>(), con.data_ptr<S>(), amp.data_ptr<S>(), sig2.data_ptr<S>(),
                  static_cast<int>(order), tol, opts, stream);
    at::Tensor sizes = at::zeros({B * tiles + groups + 1}, i64);
    int64_t* const sizes_d = sizes.data_ptr<int64_t>();
    if (trees.herm_off.defined()) sizes.narrow(0, B * tiles + groups, 1).copy_(trees.herm_off.narrow(0, trees.herm_off.size(0) - 1, 1));
    std::vector<CameraGroup> cgs(groups);
    std::vector<at::Tensor> metrics(groups), slot_offsets(groups);
    const TileGrid grid{width, height, tiles_x, tiles, log_theta, log_far};
    for (int64_t g = 0; g < groups; ++g) {
      CameraGroup& cg = cgs[g];
      cg.first = g * group;
      cg.count = std::min(group, B - cg.first);
      cg.n_valid = trees.count.data_ptr<int64_t>();
      const int64_t stride = std::max<int64_t>(1, trees.inner());  // internal nodes of a tree of N points
      metrics[g] = bytes(cg.count * stride * static_cast<int64_t>(sizeof(ItemMetric)), opts);
      for (int64_t c = 0; c < cg.count; ++c) {
        const int64_t b = cg.first + c;
        cg.tv[c] = trees.view(b);
        cg.tv[c].metric = as<ItemMetric>(metrics[g]) + c * stride;
        cg.seed[c] = static_cast<uint64_t>(st[2 * b]);
        cg.camera[c] = st[2 * b + 1];
      }
      NS_LAUNCH(group_metric_kernel, blocks_for(cg.count * stride, kThreads), kThreads, stream, cg, stride,
                as<ItemMetric>(metrics[g]));
      NS_LAUNCH_CHECK();
      // the slots' item counts and their exclusive scan (one trailing zero: the last offset is the total), and the
      // camera tiles' offsets into the group's part of `sizes`
      const int64_t slots = cg.count * tiles * kTileSlots;
      at::Tensor slot_counts = at::zeros({slots + 1}, i64);
      NS_LAUNCH(slot_items_kernel, blocks_for(slots, kThreads), kThreads, stream, cg, grid,
                slot_counts.data_ptr<int64_t>(), nullptr, nullptr, nullptr, nullptr);
      NS_LAUNCH_CHECK();
      slot_offsets[g] = at::empty({slots + 1}, i64);
      exclusive_sum(slot_counts.data_ptr<int64_t>(), slot_offsets[g].data_ptr<int64_t>(), slots + 1, opts, stream);
      NS_LAUNCH(tile_offsets_kernel, blocks_for(cg.count * tiles + 1, kThreads), kThreads, stream,
                slot_offsets[g].data_ptr<int64_t>(), cg.count * tiles, sizes_d + cg.first * tiles + g);
      NS_LAUNCH_CHECK();
    }
    const at::Tensor sizes_host = to_host(sizes);  // synchronises (the call's one read)
    tree_coefficients(trees, sizes_host.data_ptr<int64_t>()[B * tiles + groups], opts, stream);
    for (int64_t g = 0; g < groups; ++g) {
      CameraGroup& cg = cgs[g];
      const int64_t gt = cg.count * tiles;  // the group's camera tiles
      const int64_t* off_h = sizes_host.data_ptr<int64_t>() + cg.first * tiles + g;
      const int64_t* offsets = sizes_d + cg.first * tiles + g;
      for (int64_t c = 0; c < cg.count; ++c) cg.tv[c].herm_coef = trees.view(cg.first + c).herm_coef;
      const int64_t n_items = off_h[gt];
      at::Tensor items = bytes(std::max<int64_t>(n_items, 1) * static_cast<int64_t>(sizeof(TileItem)), opts);
      at::Tensor near_counts = at::zeros({gt}, opts.dtype(at::kInt));
      {
        at::Tensor raw = bytes(std::max<int64_t>(n_items, 1) * static_cast<int64_t>(sizeof(TileItem)), opts);
        at::Tensor keys = at::empty({2, std::max<int64_t>(n_items, 1)}, i64);
        at::Tensor pos = at::empty({2, std::max<int64_t>(n_items, 1)}, opts.dtype(at::kInt));
        NS_LAUNCH(slot_items_kernel, blocks_for(gt * kTileSlots, kThreads), kThreads, stream, cg, grid, nullptr,
                  slot_offsets[g].data_ptr<int64_t>(), as<TileItem>(raw), as<uint64_t>(keys), pos.data_ptr<int>());
        NS_LAUNCH_CHECK();
        sort_pairs(as<uint64_t>(keys), as<uint64_t>(keys) + keys.size(1), pos.data_ptr<int>(),
                   pos.data_ptr<int>() + pos.size(1), n_items, item_key_bits(gt), opts, stream);
        NS_LAUNCH(arrange_items_kernel, blocks_for(n_items, kThreads), kThreads, stream, as<TileItem>(raw),
                  as<uint64_t>(keys) + keys.size(1), pos.data_ptr<int>() + pos.size(1), n_items, offsets,
                  as<TileItem>(items), near_counts.data_ptr<int>());
        NS_LAUNCH_CHECK();
      }
      // pixel pass in chunks of whole camera tiles (across the group's cameras) whose bin bytes fit in
      // kBinScratchBytes (a tile larger than that is a chunk of its own)
      const int64_t chunk_items = std::max<int64_t>(kBinScratchBytes / kTilePixels, 1);
      at::Tensor bin8 = bytes(std::min(n_items, chunk_items) * kTilePixels, opts);
      PixelPass<S> pass{cg, base, Kd.data_ptr<double>(), width, height, tiles_x, tiles, static_cast<int>(m), lanes,
                        static_cast<int>(inclusion), lane_log_eps, stratified, as<TileItem>(items), offsets,
                        near_counts.data_ptr<int>(), nullptr, key_scratch.data_ptr<double>(),
                        heap_idx.data_ptr<int>(), heaps, lanes > 1 ? as<LaneStats>(lane_stats) : nullptr,
                        lanes > 1 ? merged_key.data_ptr<double>() : nullptr,
                        lanes > 1 ? merged_idx.data_ptr<int>() : nullptr,
                        lanes > 1 ? merged_rest.data_ptr<double>() : nullptr, merged, indices.data_ptr<int>(),
                        probs.data_ptr<S>(), total.data_ptr<S>(), work.data_ptr<int>()};
      for (int64_t T0 = 0; T0 < gt;) {
        int64_t T1 = T0 + 1;
        while (T1 < gt && off_h[T1 + 1] - off_h[T0] <= chunk_items) ++T1;
        if ((off_h[T1] - off_h[T0]) * kTilePixels > bin8.numel()) bin8 = bytes((off_h[T1] - off_h[T0]) * kTilePixels, opts);
        pass.bin8 = as<uint8_t>(bin8);
        NS_LAUNCH(sample_kernel<S>, blocks_for((T1 - T0) * lanes * kTilePixels, kPixelThreads), kPixelThreads, stream,
                  pass, T0, T1);
        NS_LAUNCH_CHECK();
        if (lanes > 1) {
          NS_LAUNCH(merge_prepare_kernel<S>, blocks_for((T1 - T0) * lanes * kTilePixels, kPixelThreads), kPixelThreads,
                    stream, pass, T0, T1);
          NS_LAUNCH_CHECK();
          NS_LAUNCH(merge_rank_kernel<S>, blocks_for((T1 - T0) * lanes * kTilePixels, kPixelThreads), kPixelThreads,
                    stream, pass, T0, T1);
          NS_LAUNCH_CHECK();
          NS_LAUNCH(merge_finish_kernel<S>, blocks_for((T1 - T0) * kTilePixels, kPixelThreads), kPixelThreads, stream,
                    pass, T0, T1);
          NS_LAUNCH_CHECK();
        }
        T0 = T1;
      }
    }
  });
  return {indices, probs, total, work};
}

#if defined(NSPLAT_CUDA_EMULATE)
// Test entry of the emulation build: rank_lane over P pixels' L sorted heaps (key, idx [P, L, m], cnt [P, L]);
// returns the merged heaps' m smallest entries (key [P, m] double, idx [P, m] int; unset entries NaN / -1) and each
// pixel's (m+1)-th smallest key ([P], NaN when there are at most m entries).
std::vector<at::Tensor> merge_lanes_emulated(const at::Tensor& key, const at::Tensor& idx, const at::Tensor& cnt,
                                             int64_t m) {
  const int64_t P = key.size(0), L = key.size(1), H = P * L * kTilePixels;
  const auto dbl = key.options().dtype(at::kDouble), i32 = key.options().dtype(at::kInt);
  at::Tensor heap_key = at::empty({key.size(2), H}, dbl), heap_idx = at::empty({key.size(2), H}, i32);
  std::vector<LaneStats> stats(static_cast<size_t>(H));
  const at::Tensor k = key.contiguous(), id = idx.contiguous(), c = cnt.contiguous();
  for (int64_t h = 0; h < P * L; ++h) {
    stats[static_cast<size_t>(h * kTilePixels)].cnt = c.data_ptr<int>()[h];
    for (int64_t i = 0; i < key.size(2); ++i) {
      heap_key.data_ptr<double>()[i * H + h * kTilePixels] = k.data_ptr<double>()[h * key.size(2) + i];
      heap_idx.data_ptr<int>()[i * H + h * kTilePixels] = id.data_ptr<int>()[h * key.size(2) + i];
    }
  }
  at::Tensor out_key = at::full({m, P}, NAN, dbl), out_idx = at::full({m, P}, -1, i32), rest = at::full({P}, NAN, dbl);
  for (int64_t p = 0; p < P; ++p)
    for (int lane = 0; lane < L; ++lane)
      rank_lane(heap_key.data_ptr<double>(), heap_idx.data_ptr<int>(), H, stats.data(), p * L * kTilePixels, lane,
                static_cast<int>(L), static_cast<int>(m), out_key.data_ptr<double>() + p, out_idx.data_ptr<int>() + p,
                P, rest.data_ptr<double>() + p);
  return {out_key.t().contiguous(), out_idx.t().contiguous(), rest};
}

int64_t launches_emulated() { return emu::launch_count; }
#endif

int64_t host_reads_cuda() { return host_read_count().load(); }

std::vector<at::Tensor> composite_forward_cuda(const at::Tensor& mu, const at::Tensor& con, const at::Tensor& amp,
                                               const at::Tensor& nrm, const at::Tensor& off, const at::Tensor& zc,
                                               const at::Tensor& Ks, const at::Tensor& feat, const at::Tensor& bg,
                                               const at::Tensor& indices, const at::Tensor& probs, int64_t mode) {
  const DeviceGuard guard(mu.device());
  const Stream stream = current_stream();
  const int64_t B = indices.size(0), H = indices.size(1), W = indices.size(2), m = indices.size(3);
  const int64_t C = feat.size(-1), P = H * W;
  const int64_t feat_stride = feat.dim() == 3 ? amp.size(1) * C : 0;  // [B,N,C]: camera b reads feat[b]
  auto opts = mu.options();
  at::Tensor image = at::empty({B, H, W, C}, opts);
  at::Tensor alpha = at::empty({B, H, W, 1}, opts);
  at::Tensor depth = at::empty({B, H, W, 1}, opts);
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  if (B * P == 0) return {image, alpha, depth};
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_composite_forward_cuda", [&] {
    using S = scalar_t;
    NS_LAUNCH(composite_forward_kernel<S>, blocks_for(B * P, kPixelThreads), kPixelThreads, stream,
        splats_base<S>(mu, con, amp, nrm, off, zc), Kd.data_ptr<double>(), feat.data_ptr<S>(), static_cast<int>(C),
        feat_stride, bg.data_ptr<S>(), indices.data_ptr<int>(), probs.data_ptr<S>(), static_cast<int>(m), W, P, B * P,
        static_cast<int>(mode), image.data_ptr<S>(), alpha.data_ptr<S>(), depth.data_ptr<S>());
    NS_LAUNCH_CHECK();
  });
  return {image, alpha, depth};
}

std::vector<at::Tensor> composite_backward_pixels_cuda(const at::Tensor& mu, const at::Tensor& con,
                                                       const at::Tensor& amp, const at::Tensor& nrm,
                                                       const at::Tensor& off, const at::Tensor& zc,
                                                       const at::Tensor& Ks, const at::Tensor& feat,
                                                       const at::Tensor& bg, const at::Tensor& indices,
                                                       const at::Tensor& probs, int64_t mode, int64_t estimator,
                                                       const at::Tensor& g_img, const at::Tensor& g_alpha,
                                                       const at::Tensor& g_depth) {
  const DeviceGuard guard(mu.device());
  const Stream stream = current_stream();
  const int64_t B = indices.size(0), H = indices.size(1), W = indices.size(2), m = indices.size(3);
  const int64_t C = feat.size(-1), P = H * W;
  const int64_t feat_stride = feat.dim() == 3 ? amp.size(1) * C : 0;  // [B,N,C]: camera b reads feat[b]
  auto opts = mu.options();
  at::Tensor dalpha = at::zeros({B, H, W, m}, opts);
  at::Tensor wf = at::zeros({B, H, W, m}, opts);
  at::Tensor bgw = at::empty({B, H, W, 1}, opts);
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  if (B * P == 0) return {dalpha, wf, bgw};
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_composite_backward_pixels_cuda", [&] {
    using S = scalar_t;
    NS_LAUNCH(backward_pixels_kernel<S>, blocks_for(B * P, kPixelThreads), kPixelThreads, stream,
        splats_base<S>(mu, con, amp, nrm, off, zc), Kd.data_ptr<double>(), feat.data_ptr<S>(), static_cast<int>(C),
        feat_stride, bg.data_ptr<S>(), indices.data_ptr<int>(), probs.data_ptr<S>(), static_cast<int>(m), W, P, B * P,
        static_cast<int>(mode), static_cast<int>(estimator), g_img.data_ptr<S>(), g_alpha.data_ptr<S>(),
        g_depth.data_ptr<S>(), dalpha.data_ptr<S>(), wf.data_ptr<S>(), bgw.data_ptr<S>());
    NS_LAUNCH_CHECK();
  });
  return {dalpha, wf, bgw};
}

std::vector<at::Tensor> composite_backward_points_cuda(const at::Tensor& mu, const at::Tensor& con,
                                                       const at::Tensor& amp, const at::Tensor& nrm,
                                                       const at::Tensor& off, const at::Tensor& zc,
                                                       const at::Tensor& Ks, const at::Tensor& entries,
                                                       const at::Tensor& seg, const at::Tensor& dalpha,
                                                       const at::Tensor& wf, const at::Tensor& g_img,
                                                       const at::Tensor& g_depth, int64_t width, int64_t height,
                                                       int64_t estimator, bool per_camera_features) {
  const DeviceGuard guard(mu.device());
  const Stream stream = current_stream();
  const int64_t B = amp.size(0), N = amp.size(1), C = g_img.size(3), m = dalpha.size(3), P = width * height;
  auto opts = mu.options();
  std::vector<at::Tensor> out = {at::zeros({B, N, 2}, opts), at::zeros({B, N, 3}, opts), at::zeros({B, N}, opts),
                                 at::zeros({B, N, 3}, opts), at::zeros({B, N}, opts),    at::zeros({B, N}, opts),
                                 per_camera_features ? at::zeros({B, N, C}, opts) : at::zeros({N, C}, opts)};
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  if (N == 0 || entries.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(mu.scalar_type(), "nsplat_composite_backward_points_cuda", [&] {
    using S = scalar_t;
    PointGrads<S> g{out[0].data_ptr<S>(), out[1].data_ptr<S>(), out[2].data_ptr<S>(), out[3].data_ptr<S>(),
                    out[4].data_ptr<S>(), out[5].data_ptr<S>(), out[6].data_ptr<S>()};
    NS_LAUNCH(backward_points_kernel<S>, blocks_for(N, kPixelThreads), kPixelThreads, stream,
        splats_base<S>(mu, con, amp, nrm, off, zc), Kd.data_ptr<double>(), entries.data_ptr<int64_t>(),
        seg.data_ptr<int64_t>(), dalpha.data_ptr<S>(), wf.data_ptr<S>(), g_img.data_ptr<S>(), g_depth.data_ptr<S>(),
        m, C, width, P, estimator == kPaper, per_camera_features, g);
    NS_LAUNCH_CHECK();
  });
  return out;
}

}  // namespace nsplat
