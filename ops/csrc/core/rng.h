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

// Stratified draws (variance reduction across pixels). Every pixel of a camera shares one uniform per
// point, h_k = uniform01(camera_stream, k), shifted by the pixel's rank-1 lattice value phi(x):
// u = frac(h_k + phi(x)). Within a pixel the u_k stay i.i.d. uniform (a common shift of independent
// uniforms mod 1), so every per-pixel sample is still an exact SPS draw; across pixels a point's draws
// are a shifted low-discrepancy sequence instead of independent ones.
NS_HD uint64_t camera_stream(uint64_t seed, int64_t camera) {
  return mix64(mix64(seed + 0xD1B54A32D192ED03ull * static_cast<uint64_t>(camera + 1)) ^ 0x5851F42D4C957F2Dull);
}

// phi(col, row) = frac(a1 col + a2 row) with the R2 sequence's constants (plastic number).
NS_HD double lattice_shift(int64_t col, int64_t row) {
  double t = 0.7548776662466927 * static_cast<double>(col) + 0.5698402909980532 * static_cast<double>(row);
  return t - floor(t);
}

// The per-pixel draw context: `shift` < 0 marks independent draws (u = uniform01(stream, point)).
struct Draw {
  uint64_t stream;
  double shift;
};

NS_HD Draw pixel_draw(uint64_t seed, int64_t camera, int64_t pixel, int64_t width, bool stratified) {
  if (!stratified) return Draw{pixel_stream(seed, camera, pixel), -1.0};
  return Draw{camera_stream(seed, camera), lattice_shift(pixel % width, pixel / width)};
}

NS_HD double draw_uniform(const Draw& d, int64_t point) {
  double u = uniform01(d.stream, point);
  if (d.shift < 0.0) return u;
  u += d.shift;
  u -= floor(u);
  return u > 0.0 ? u : 5.551115123125783e-17;  // keep u in (0, 1)
}

}  // namespace nsplat
