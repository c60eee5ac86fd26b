// View-dependent colour, one point at a time: forward and hand-derived backward of nsplat/sh.py's view_colour
// (whose pure-PyTorch `view_colour_torch` is the reference, tests/test_sh.py and tests/test_op_cuda.py). Host and
// device code: the CPU backend (cpu/view_colour_cpu.cpp) and the CUDA backend (cuda/projection_cuda.cu) run these
// functions in their own loops.
//
// RGB = max(0, f_0 + sum_{j >= 1} f_j Y_j(d)), d the unit direction from the camera centre -R^T t to the point,
// Y_j the real SH basis of bands 1..L (L <= 3) in nsplat/sh.py's order; features [N, F] hold 3 (L+1)^2 leading
// SH coefficients per point (F may be larger: the rest get zero gradient).
#pragma once
#include "common.h"

namespace nsplat {

constexpr int64_t kColourBlock = 512;  // points per block of the viewmat-gradient sums
constexpr int kMaxBasis = 15;          // bands 1..3

// The basis constants of nsplat/sh.py.
constexpr double kC1 = 0.4886025119029199;   // sqrt(3 / 4pi)
constexpr double kC2 = 1.0925484305920792;   // sqrt(15 / pi) / 2
constexpr double kC20 = 0.31539156525252005;  // sqrt(5 / pi) / 4
constexpr double kC22 = 0.5462742152960396;   // sqrt(15 / pi) / 4
constexpr double kC30 = 0.5900435899266435;   // sqrt(35 / 2pi) / 4
constexpr double kC31 = 2.890611442640554;    // sqrt(105 / pi) / 2
constexpr double kC32 = 0.4570457994644658;   // sqrt(21 / 2pi) / 4
constexpr double kC33 = 0.3731763325901154;   // sqrt(7 / pi) / 4

// Basis values Y[j] and, when D is not null, their gradients D[3 j + (0, 1, 2)] w.r.t. (x, y, z).
template <typename S>
NS_HD void basis(S x, S y, S z, int degree, S* Y, S* D) {
  const S c1 = S(kC1);
  Y[0] = c1 * y;
  Y[1] = c1 * z;
  Y[2] = c1 * x;
  if (D) {
    const S d[9] = {0, c1, 0, 0, 0, c1, c1, 0, 0};
    for (int i = 0; i < 9; ++i) D[i] = d[i];
  }
  if (degree < 2) return;
  const S c2 = S(kC2), c20 = S(kC20), c22 = S(kC22);
  const S xx = x * x, yy = y * y, zz = z * z;
  Y[3] = c2 * x * y;
  Y[4] = c2 * y * z;
  Y[5] = c20 * (S(3) * zz - S(1));
  Y[6] = c2 * x * z;
  Y[7] = c22 * (xx - yy);
  if (D) {
    const S d[15] = {c2 * y, c2 * x, 0, 0, c2 * z, c2 * y, 0, 0, S(6) * c20 * z, c2 * z, 0, c2 * x,
                     S(2) * c22 * x, -S(2) * c22 * y, 0};
    for (int i = 0; i < 15; ++i) D[9 + i] = d[i];
  }
  if (degree < 3) return;
  const S c30 = S(kC30), c31 = S(kC31), c32 = S(kC32), c33 = S(kC33);
  Y[8] = c30 * y * (S(3) * xx - yy);
  Y[9] = c31 * x * y * z;
  Y[10] = c32 * y * (S(5) * zz - S(1));
  Y[11] = c33 * z * (S(5) * zz - S(3));
  Y[12] = c32 * x * (S(5) * zz - S(1));
  Y[13] = S(0.5) * c31 * z * (xx - yy);
  Y[14] = c30 * x * (xx - S(3) * yy);
  if (D) {
    const S d[21] = {c30 * S(6) * x * y,       c30 * S(3) * (xx - yy),    0,
                     c31 * y * z,              c31 * x * z,               c31 * x * y,
                     0,                        c32 * (S(5) * zz - S(1)),  c32 * S(10) * y * z,
                     0,                        0,                         c33 * (S(15) * zz - S(3)),
                     c32 * (S(5) * zz - S(1)), 0,                         c32 * S(10) * x * z,
                     c31 * x * z,              -c31 * y * z,              S(0.5) * c31 * (xx - yy),
                     c30 * S(3) * (xx - yy),   -c30 * S(6) * x * y,       0};
    for (int i = 0; i < 21; ++i) D[24 + i] = d[i];
  }
}

// The camera centre -R^T t of a world-to-camera matrix.
template <typename S>
NS_HD void centre(const S* V, S* c) {
  for (int i = 0; i < 3; ++i) c[i] = -(V[i] * V[3] + V[4 + i] * V[7] + V[8 + i] * V[11]);
}

template <typename S>
struct Dir {
  S v[3], len, d[3];
};

template <typename S>
NS_HD Dir<S> direction(const S* mean, const S* c) {
  Dir<S> r;
  for (int i = 0; i < 3; ++i) r.v[i] = mean[i] - c[i];
  const S n = ssqrt(r.v[0] * r.v[0] + r.v[1] * r.v[1] + r.v[2] * r.v[2]);
  r.len = n < S(1e-12) ? S(1e-12) : n;  // as torch.nn.functional.normalize
  for (int i = 0; i < 3; ++i) r.d[i] = r.v[i] / r.len;
  return r;
}


// Point k's RGB into out[3 k ..]: features fk [F] (k's row), the camera centre c.
template <typename S>
NS_HD void colour_point(const S* fk, const S* mean, const S* c, int degree, S* out) {
  const int nb = (degree + 1) * (degree + 1) - 1;
  const Dir<S> r = direction(mean, c);
  S Y[kMaxBasis];
  basis(r.d[0], r.d[1], r.d[2], degree, Y, static_cast<S*>(nullptr));
  for (int ch = 0; ch < 3; ++ch) {
    S acc = S(0);
    for (int j = 0; j < nb; ++j) acc += Y[j] * fk[3 * (j + 1) + ch];
    const S rgb = fk[ch] + acc;
    out[ch] = rgb > S(0) ? rgb : S(0);
  }
}

// The backward of point k given g [3] (its RGB's gradient): the features' gradient into gfk [F], the mean's into
// gm [3]; returns the latter (the gradient of v = mean - c, whose negative sum over points is the centre's).
template <typename S>
NS_HD void colour_point_backward(const S* fk, const S* mean, const S* c, int degree, int64_t F, const S* g, S* gfk,
                                 S* gm) {
  const int nb = (degree + 1) * (degree + 1) - 1;
  const Dir<S> r = direction(mean, c);
  S Y[kMaxBasis], D[3 * kMaxBasis];
  basis(r.d[0], r.d[1], r.d[2], degree, Y, D);
  S gy[3];  // gradient of the pre-clamp RGB (clamp_min passes it where the value is >= 0)
  for (int ch = 0; ch < 3; ++ch) {
    S acc = S(0);
    for (int j = 0; j < nb; ++j) acc += Y[j] * fk[3 * (j + 1) + ch];
    gy[ch] = fk[ch] + acc >= S(0) ? g[ch] : S(0);
    gfk[ch] = gy[ch];
  }
  S gd[3] = {0, 0, 0};
  for (int j = 0; j < nb; ++j) {
    S gb = S(0);
    for (int ch = 0; ch < 3; ++ch) {
      gfk[3 * (j + 1) + ch] = Y[j] * gy[ch];
      gb += fk[3 * (j + 1) + ch] * gy[ch];
    }
    for (int i = 0; i < 3; ++i) gd[i] += gb * D[3 * j + i];
  }
  for (int64_t i = 3 * (nb + 1); i < F; ++i) gfk[i] = S(0);
  // d = v / max(|v|, 1e-12): the gradient projected off d, over |v| (no projection below the floor)
  const bool floored = r.len > ssqrt(r.v[0] * r.v[0] + r.v[1] * r.v[1] + r.v[2] * r.v[2]);
  const S dot = floored ? S(0) : r.d[0] * gd[0] + r.d[1] * gd[1] + r.d[2] * gd[2];
  for (int i = 0; i < 3; ++i) gm[i] = (gd[i] - r.d[i] * dot) / r.len;
}

// The viewmat's gradient [16] from the centre's, gc = -sum_k g_v (c = -R^T t: c_i = -sum_r R[r][i] t_r).
template <typename S>
NS_HD void write_viewmat_grad(const S* V, const double* gc, S* gv) {
  for (int i = 0; i < 16; ++i) gv[i] = S(0);
  for (int r = 0; r < 3; ++r) {
    double gt = 0.0;
    for (int i = 0; i < 3; ++i) {
      gv[4 * r + i] = static_cast<S>(-gc[i] * static_cast<double>(V[4 * r + 3]));
      gt -= gc[i] * static_cast<double>(V[4 * r + i]);
    }
    gv[4 * r + 3] = static_cast<S>(gt);
  }
}

}  // namespace nsplat
