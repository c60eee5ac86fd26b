// Shared definitions for the host (g++/OpenMP) and device (nvcc) builds of the splatting core.
#pragma once
#include <cmath>
#include <cstdint>
#include <cstring>

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
constexpr double kMinTotal = 0x1p-24;  // pixels whose total size measure is below this (half an ulp of a float 1) get no sample
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
NS_HD float ssqrt(float x) { return sqrtf(x); }
NS_HD double ssqrt(double x) { return sqrt(x); }
template <typename S>
NS_HD bool sfinite(S x) {
#if defined(__CUDA_ARCH__)
  return isfinite(x);
#else
  return std::isfinite(x);
#endif
}

// 2^(j/64), j = 0..63, rounded to nearest, and the rounding remainders (host exp below).
constexpr double kExp2Table[64] = {
    1.0, 1.0108892860517005, 1.0218971486541166, 1.0330248790212284,
    1.0442737824274138, 1.0556451783605572, 1.0671404006768237, 1.0787607977571199,
    1.0905077326652577, 1.102382583307841, 1.1143867425958924, 1.1265216186082418,
    1.1387886347566916, 1.1511892299529827, 1.1637248587775775, 1.1763969916502812,
    1.189207115002721, 1.202156731452703, 1.215247359980469, 1.22848053610687,
    1.241857812073484, 1.255380757024691, 1.2690509571917332, 1.2828700160787783,
    1.2968395546510096, 1.3109612115247644, 1.3252366431597413, 1.339667524053303,
    1.3542555469368927, 1.3690024229745905, 1.383909881963832, 1.3989796725383112,
    1.4142135623730951, 1.42961333839197, 1.4451808069770467, 1.460917794180647,
    1.4768261459394993, 1.4929077282912648, 1.5091644275934228, 1.5255981507445384,
    1.5422108254079407, 1.559004400237837, 1.5759808451078865, 1.593142151342267,
    1.6104903319492543, 1.6280274218573478, 1.645755478153965, 1.6636765803267364,
    1.681792830507429, 1.7001063537185235, 1.718619298122478, 1.7373338352737062,
    1.7562521603732995, 1.7753764925265212, 1.7947090750031072, 1.8142521755003989,
    1.8340080864093424, 1.8539791250833855, 1.8741676341103, 1.8945759815869656,
    1.9152065613971474, 1.9360617934922943, 1.9571441241754002, 1.978456026387951};

constexpr double kExp2TableLo[64] = {
    0.0, -1.5234778603368577e-17, 5.109225028973444e-17, 7.600838874027088e-18,
    8.551889705537965e-17, 1.759325738772092e-18, -7.899853966841582e-17, -6.656660436056593e-17,
    -3.046782079812471e-17, 5.2660368715706944e-17, 1.0410278456845571e-16, 5.165856758795457e-17,
    8.912812676025408e-17, 3.250710218863827e-17, 3.8292048369240935e-17, 5.554203254218079e-17,
    3.982015231465646e-17, 6.644981499252301e-17, -7.712630692681488e-17, -1.89878163130253e-17,
    4.658027591836937e-17, -6.7113898212968784e-18, 2.667932131342186e-18, 1.713594918243561e-17,
    2.5382502794888315e-17, -7.181536135519454e-17, -2.8587312100388614e-17, 8.927282594831732e-17,
    7.70094837980299e-17, 9.593797919118849e-17, -6.770511658794786e-17, -9.614213209051323e-17,
    -9.667293313452913e-17, -1.2031642489053655e-17, -3.0237581349939873e-17, -5.600377186075216e-17,
    -3.483994556892796e-17, 1.4192920154284036e-17, -1.016455327754295e-16, -1.1024941712342561e-16,
    7.949834809697621e-17, 3.7812070533575275e-17, -1.0136916471278304e-17, -1.0094406542311964e-16,
    2.4707192569797888e-17, -6.712955084707084e-17, -1.0125679913674773e-16, 5.8909926967131e-17,
    8.199010020581497e-17, -8.0237193703977e-18, -1.851380418263111e-17, 3.164389299292957e-17,
    2.960140695448873e-17, 6.429731796556572e-17, 1.8227458427912087e-17, -9.969531538920349e-17,
    3.283107224245627e-17, 9.761887490727594e-17, -6.122763413004143e-17, 3.4034035352165297e-17,
    -1.0619946056195963e-16, 1.0332385960676326e-16, 8.960767791036668e-17, 4.0388753109278167e-17};

// exp(x) of the sampler's hot paths (one per exact kernel evaluation). Device: the CUDA library's exp. Host:
// inlined instead of two library calls (glibc's errno wrapper and its kernel): x = (64 n + j) ln2/64 + r with
// a two-constant (Cody-Waite) reduction, |r| <= ln2/128, exp(x) = 2^n (t_j + t_j p(r)), t_j = 2^(j/64) as a
// double plus its remainder, p of degree 5 (truncation < 4e-17 relative): within 1 ulp of exp(x)
// (tests/test_op_sampler.py). Arguments outside
// (-708, 709) (overflow, subnormal results, infinities, NaN) go to the library exp.
NS_HD double fast_exp(double x) {
#if defined(__CUDA_ARCH__)
  return exp(x);
#else
  if (!(x > -708.0 && x < 709.0)) return exp(x);
  constexpr double kShift = 6755399441055744.0;  // 1.5 * 2^52: adding it rounds to an integer in the low bits
  const double kd = x * 92.33248261689366 + kShift;  // 64 / ln2
  uint64_t kbits;
  std::memcpy(&kbits, &kd, sizeof kbits);
  const int64_t k = static_cast<int64_t>(kbits << 13) >> 13;  // the rounded integer (sign-extended low bits)
  const double kr = kd - kShift;
  const double r = (x - kr * 0.010830424696223417) - kr * 2.572804622327669e-14;  // ln2/64 as hi + lo
  const double q = r + r * r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0))));
  const double t = kExp2Table[k & 63];
  const uint64_t sbits = static_cast<uint64_t>((k >> 6) + 1023) << 52;
  double scale;
  std::memcpy(&scale, &sbits, sizeof scale);
  return (t + (kExp2TableLo[k & 63] + t * q)) * scale;
#endif
}

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
