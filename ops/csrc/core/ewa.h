// Per-pixel evaluation of a projected EWA splat (mirrors ops/reference.py).
//
// A projected splat has screen mean mu (2), conic (a, b, c) = Sigma^-1 entries, amplitude A, camera-space
// unit normal n (3), plane offset n.q and centre depth z. At pixel centre x:
//   alpha(x) = min(alpha_max, A exp(-q/2)),  q = a dx^2 + 2 b dx dy + c dy^2,  d = x - mu
//   depth(x) = (n.q) / (n.r) for the pixel ray r = K^-1 (x, 1) (z = 1), or z when the ray is within
//              kParallelCos of parallel to the plane or meets it behind the camera.
#pragma once
#include "common.h"

namespace nsplat {

// Pixel ray of an upper-triangular K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] through (u, v): (rx, ry, 1).
struct Ray {
  double x, y, norm;
};

NS_HD Ray pixel_ray(const double* K, double u, double v) {
  Ray r;
  r.y = (v - K[5]) / K[4];
  r.x = (u - K[2] - K[1] * r.y) / K[0];
  r.norm = sqrt(r.x * r.x + r.y * r.y + 1.0);
  return r;
}

template <typename S>
NS_HD double quad_form(const S* mu, const S* con, double u, double v) {
  double dx = u - static_cast<double>(mu[0]);
  double dy = v - static_cast<double>(mu[1]);
  return static_cast<double>(con[0]) * dx * dx + 2.0 * static_cast<double>(con[1]) * dx * dy +
         static_cast<double>(con[2]) * dy * dy;
}

// log of the sampler's size measure lambda = alpha (double precision, no underflow).
template <typename S>
NS_HD double log_size(const S* mu, const S* con, double logA, double u, double v) {
  return dmin(log(kAlphaMax), logA - 0.5 * quad_form(mu, con, u, v));
}

// Splat alpha in the working precision S; `clamped` tells whether alpha_max was hit (zero gradient).
template <typename S>
NS_HD S splat_alpha(const S* mu, const S* con, S amp, S u, S v, bool* clamped) {
  S dx = u - mu[0], dy = v - mu[1];
  S q = con[0] * dx * dx + S(2) * con[1] * dx * dy + con[2] * dy * dy;
  S raw = amp * sexp(S(-0.5) * q);
  *clamped = raw > S(kAlphaMax);
  return *clamped ? S(kAlphaMax) : raw;
}

// Per-pixel depth of a splat; `on_plane` tells whether the ray-plane hit (not the centre depth) was used.
template <typename S>
NS_HD S splat_depth(const S* n, S offset, S zc, const Ray& r, bool* on_plane, S* dot_out) {
  S dot = n[0] * S(r.x) + n[1] * S(r.y) + n[2];
  S t = dot != S(0) ? offset / dot : S(0);
  *on_plane = sabs(dot) >= S(kParallelCos * r.norm) && t > S(0);
  *dot_out = dot;
  return *on_plane ? t : zc;
}

}  // namespace nsplat
