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

// A point's 64-bit draw is two 32-bit hashes of (stream, point): `draw_hi`, from the stream's low word, and
// `draw_lo`, from its high word (lowbias32, a bijection of 32-bit words: within a pixel, distinct points get
// distinct high words). The CPU sampler's vector filter only needs draw_hi: u lies in [hi 2^-32, (hi + 1) 2^-32).
NS_HD uint32_t hash32(uint32_t x) {
  x ^= x >> 16;
  x *= 0x7FEB352Du;
  x ^= x >> 15;
  x *= 0x846CA68Bu;
  return x ^ (x >> 16);
}

NS_HD uint32_t draw_hi(uint64_t stream, uint32_t point) {
  return hash32(static_cast<uint32_t>(stream) + point * 0x9E3779B9u);
}

NS_HD uint32_t draw_lo(uint64_t stream, uint32_t point) {
  return hash32(static_cast<uint32_t>(stream >> 32) ^ (point * 0x85EBCA6Bu));
}

// u for point `point` of a pixel stream: the draw's top 53 bits, ((hi 2^21 + (lo >> 11)) + 0.5) 2^-53 in (0, 1).
NS_HD double uniform_of(uint32_t hi, uint32_t lo) {
  const uint64_t h = (static_cast<uint64_t>(hi) << 21) | (lo >> 11);
  return (static_cast<double>(h) + 0.5) * 1.1102230246251565e-16;
}

NS_HD double uniform01(uint64_t stream, int64_t point) {
  const uint32_t k = static_cast<uint32_t>(point);
  return uniform_of(draw_hi(stream, k), draw_lo(stream, k));
}


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

// Stratified u of a point whose camera-wide uniform is `base`, at a pixel with lattice shift `shift`.
NS_HD double shifted_uniform(double base, double shift) {
  double u = base + shift;
  u -= floor(u);
  return u > 0.0 ? u : 5.551115123125783e-17;  // keep u in (0, 1)
}

NS_HD double draw_uniform(const Draw& d, int64_t point) {
  const double u = uniform01(d.stream, point);
  return d.shift < 0.0 ? u : shifted_uniform(u, d.shift);
}

}  // namespace nsplat
