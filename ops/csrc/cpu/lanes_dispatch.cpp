// Run-time choice of the tile search's instruction set (lanes_api.h): the widest this CPU runs, unless the
// environment variable NSPLAT_CPU_SIMD (or the caller) names another. All of them compute the same bits.
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>

#include "lanes_api.h"

namespace nsplat {
namespace {

struct Isa {
  const char* name;
  LaneSearchFn fn;
  bool (*runs)();
};

bool always() { return true; }
#if defined(__x86_64__)
bool has_avx2() { return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"); }
bool has_avx512() {
  return has_avx2() && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
         __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512bw");
}
#endif

const Isa kIsas[] = {
    {"base", lane_search_base, always},
#if defined(__x86_64__)
    {"avx2", lane_search_avx2, has_avx2},
    {"avx512", lane_search_avx512, has_avx512},
#endif
};
constexpr int kIsaCount = sizeof(kIsas) / sizeof(kIsas[0]);

const char* const* names() {
  static const char* n[kIsaCount];
  for (int i = 0; i < kIsaCount; ++i) n[i] = kIsas[i].name;
  return n;
}

}  // namespace

const char* const* lane_isa_names(int* count) {
  *count = kIsaCount;
  return names();
}

LaneSearchFn lane_search(const char* name, const char** chosen) {
  if (std::strcmp(name, "auto") == 0) {
    const char* env = std::getenv("NSPLAT_CPU_SIMD");
    if (env && *env && std::strcmp(env, "auto") != 0) return lane_search(env, chosen);
    for (int i = kIsaCount - 1; i >= 0; --i)
      if (kIsas[i].runs()) {
        *chosen = kIsas[i].name;
        return kIsas[i].fn;
      }
  }
  std::string known;
  for (int i = 0; i < kIsaCount; ++i) {
    if (std::strcmp(name, kIsas[i].name) == 0) {
      if (!kIsas[i].runs())
        throw std::invalid_argument(std::string("NSPLAT_CPU_SIMD: this CPU cannot run '") + name + "'");
      *chosen = kIsas[i].name;
      return kIsas[i].fn;
    }
    known += std::string(i ? ", " : "") + kIsas[i].name;
  }
  throw std::invalid_argument(std::string("NSPLAT_CPU_SIMD: expected auto or one of ") + known + ", got '" + name +
                              "'");
}

}  // namespace nsplat
