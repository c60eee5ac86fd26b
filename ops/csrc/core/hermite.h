// Hermite (fast Gauss transform) expansions of a tree node's isotropic majorant
//   G(x) = sum_j A_j exp(-|x - mu_j|^2 / (2 h^2)),  h^2 = max_j sigma_max,j^2,
// about the node's box centre c, truncated at order p per dimension (p^2 coefficients):
//   G(x) ~= sum_{a,b < p} C_ab h_a(t_x) h_b(t_y),  t = (x - c) / (sqrt(2) h),
//   C_ab = sum_j A_j s_x^a s_y^b / (a! b!),         s = (mu_j - c) / (sqrt(2) h),
// with Hermite functions h_n(t) = H_n(t) exp(-t^2) (generating function of H_n).
//
// Truncation rule (derived from Cramer's inequality |H_n(t)| exp(-t^2/2) <= K 2^(n/2) sqrt(n!),
// K = 1.086435): with rho = sqrt(2) max|s| = (box half-extent) / h and rho < sqrt(p+1), the 1-D tail
// is R_p = K rho^p / sqrt(p!) / (1 - rho / sqrt(p+1)), and the 2-D tensor truncation error is at most
// sum_j A_j * (R_p + (1 + R_p) R_p). A node gets the smallest p <= p_max with relative bound <= tol,
// or no expansion (p = 0) when none qualifies (the node is too wide for its bandwidth).
#pragma once
#include "common.h"

namespace nsplat {

constexpr double kCramer = 1.0865;

NS_HD double hermite_rel_error(double rho, int p) {
  if (rho >= sqrt(static_cast<double>(p + 1))) return INFINITY;
  double term = 1.0;  // rho^p / sqrt(p!)
  for (int n = 1; n <= p; ++n) term *= rho / sqrt(static_cast<double>(n));
  double r = kCramer * term / (1.0 - rho / sqrt(static_cast<double>(p + 1)));
  return r + (1.0 + r) * r;
}

// Smallest order meeting `tol`, or 0 for "no expansion" (hermite_rel_error for p = 1, 2, ..., its product term
// carried from one order to the next: the same operations, so the same bits).
NS_HD int hermite_order(double rho, double tol, int pmax) {
  if (rho >= sqrt(static_cast<double>(pmax + 1))) return 0;
  double term = 1.0;  // rho^p / sqrt(p!)
  for (int p = 1; p <= pmax; ++p) {
    term *= rho / sqrt(static_cast<double>(p));
    if (rho >= sqrt(static_cast<double>(p + 1))) continue;
    const double r = kCramer * term / (1.0 - rho / sqrt(static_cast<double>(p + 1)));
    if (r + (1.0 + r) * r <= tol) return p;
  }
  return 0;
}

// Adds point (x, y, amp) to the p x p coefficients `coef` of an expansion about (cx, cy).
NS_HD void hermite_accumulate(double* coef, int p, double cx, double cy, double inv_s2h, double x, double y,
                              double amp) {
  double sx = (x - cx) * inv_s2h, sy = (y - cy) * inv_s2h;
  double py[kMaxHermiteOrder];
  py[0] = 1.0;
  for (int b = 1; b < p; ++b) py[b] = py[b - 1] * sy / b;
  double pxa = amp;
  for (int a = 0; a < p; ++a) {
    for (int b = 0; b < p; ++b) coef[a * p + b] += pxa * py[b];
    pxa *= sx / (a + 1);
  }
}

NS_HD void hermite_functions(double t, int p, double* h) {
  h[0] = exp(-t * t);
  if (p > 1) h[1] = 2.0 * t * h[0];
  for (int n = 1; n + 1 < p; ++n) h[n + 1] = 2.0 * t * h[n] - 2.0 * n * h[n - 1];
}

NS_HD double hermite_eval(const double* coef, int p, double cx, double cy, double inv_s2h, double u, double v) {
  double hx[kMaxHermiteOrder], hy[kMaxHermiteOrder];
  hermite_functions((u - cx) * inv_s2h, p, hx);
  hermite_functions((v - cy) * inv_s2h, p, hy);
  double sum = 0.0;
  for (int a = 0; a < p; ++a) {
    double row = 0.0;
    for (int b = 0; b < p; ++b) row += coef[a * p + b] * hy[b];
    sum += row * hx[a];
  }
  return sum;
}

}  // namespace nsplat
