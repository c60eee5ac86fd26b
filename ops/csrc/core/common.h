// Shared definitions for the host (g++/OpenMP) and device (nvcc) builds of the splatting core.
#pragma once
#include <cmath>
#include <cstdint>

#if defined(__CUDACC__)
#define NS_HD __host__ __device__ __forceinline__
#else
#define NS_HD inline
#endif

namespace nsplat {

// Model constants (mirrored in ops/projection.py and documented in docs/op.md).
constexpr double kAlphaMax = 0.99;      // alpha clamp of a single splat
constexpr double kParallelCos = 1e-2;   // ray/plane cosine below which the centre depth is used
// Sampler constants.
constexpr double kMinTotal = 1e-10;     // pixels whose total size measure is below this get no sample
constexpr double kMinProb = 1e-8;       // floor on pi in the Horvitz-Thompson weights 1/pi
constexpr int kLeafSize = 8;            // search_subtree evaluates nodes with at most this many points exactly
constexpr int kStackSize = 72;          // DFS stack; the radix tree over 64-bit keys has depth <= 64
constexpr int kMaxHermiteOrder = 16;    // per-dimension expansion order cap (validated in Python)

enum Composite : int { kAlpha = 0, kAdditive = 1 };
enum Estimator : int { kHT = 0, kPaper = 1, kSampled = 2 };
enum Inclusion : int { kThreshold = 0, kPips = 1 };  // sps.h: finalize_pixel

NS_HD double dmin(double a, double b) { return a < b ? a : b; }
NS_HD double dmax(double a, double b) { return a > b ? a : b; }
NS_HD int imin(int a, int b) { return a < b ? a : b; }
NS_HD int imax(int a, int b) { return a > b ? a : b; }

// Precision-preserving overloads for the working type S (float or double).
NS_HD float sexp(float x) { return expf(x); }
NS_HD double sexp(double x) { return exp(x); }
NS_HD float sabs(float x) { return fabsf(x); }
NS_HD double sabs(double x) { return fabs(x); }

// log(exp(a) + exp(b)) without overflow; -inf is the neutral element.
NS_HD double log_add_exp(double a, double b) {
  if (a == -INFINITY) return b;
  if (b == -INFINITY) return a;
  double m = a > b ? a : b;
  return m + log1p(exp(-fabs(a - b)));
}

NS_HD int clz64(uint64_t x) {
#if defined(__CUDA_ARCH__)
  return __clzll(static_cast<long long>(x));
#else
  return x ? __builtin_clzll(x) : 64;
#endif
}

}  // namespace nsplat
