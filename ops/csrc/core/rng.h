// Counter-based uniforms u(seed, camera, pixel, point): a point's draw does not depend on the order
// in which the tree visits points. Mirrored bit for bit by ops/rng.py.
#pragma once
#include "common.h"

namespace nsplat {

// SplitMix64 finaliser.
NS_HD uint64_t mix64(uint64_t z) {
  z += 0x9E3779B97F4A7C15ull;
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

// Per-(seed, camera, pixel) stream state.
NS_HD uint64_t pixel_stream(uint64_t seed, int64_t camera, int64_t pixel) {
  uint64_t s = mix64(seed + 0xD1B54A32D192ED03ull * static_cast<uint64_t>(camera + 1));
  return mix64(s + static_cast<uint64_t>(pixel));
}

// u for point `point` of a pixel stream: ((h >> 11) + 0.5) * 2^-53 in (0, 1).
NS_HD double uniform01(uint64_t stream, int64_t point) {
  uint64_t h = mix64(stream + static_cast<uint64_t>(point));
  return (static_cast<double>(h >> 11) + 0.5) * 1.1102230246251565e-16;
}

NS_HD double log_uniform(uint64_t stream, int64_t point) { return log(uniform01(stream, point)); }

}  // namespace nsplat
