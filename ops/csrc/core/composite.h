// Compositing of a pixel's sample (slots in front-to-back order, -1 = empty) and its backward.
//
// alpha:    I = sum_j w_j f_j + T_end bg,  w_j = alpha_j T_j,  T_j = prod_{i<j} (1 - alpha_i),
//           alpha_out = 1 - T_end,  depth_out = sum_j w_j d_j.
// additive: I = sum_j alpha_j f_j / pi_j + (1 - sum_j alpha_j / pi_j) bg  (Horvitz-Thompson weighted),
//           alpha_out = sum_j alpha_j / pi_j,  depth_out = sum_j alpha_j d_j / pi_j.
//
// Backward, pass 1 (per pixel): for every slot the loss derivative of the unweighted term with respect
// to the splat's alpha and its feature weight, multiplied by the estimator weight
// (ht, paper: 1 / max(pi, kMinProb); sampled: 1). Pass 2 (per point) chains these through the kernel
// to the projected parameters (splat_grad_entry).
#pragma once
#include "common.h"
#include "ewa.h"
#include "sps.h"

namespace nsplat {

template <typename S>
NS_HD S ht_weight(S pi) {
  return S(1) / (pi > S(kMinProb) ? pi : S(kMinProb));
}

template <typename S>
NS_HD void composite_pixel(const SplatsView<S>& P, const S* feat, int C, const S* bg, const int* idx, const S* prob,
                           int m, S u, S v, const Ray& ray, int mode, S* img, S* alpha_out, S* depth_out) {
  for (int c = 0; c < C; ++c) img[c] = S(0);
  S T = S(1), asum = S(0), dep = S(0);
  for (int j = 0; j < m; ++j) {
    int k = idx[j];
    if (k < 0) break;
    bool clamped, on_plane;
    S dot;
    S a = splat_alpha(P.mu + 2 * k, P.con + 3 * k, P.amp[k], u, v, &clamped);
    S d = splat_depth(P.nrm + 3 * k, P.off[k], P.zc[k], ray, &on_plane, &dot);
    S w = mode == kAlpha ? a * T : a * ht_weight(prob[j]);
    const S* f = feat + static_cast<int64_t>(k) * C;
    for (int c = 0; c < C; ++c) img[c] += w * f[c];
    dep += w * d;
    if (mode == kAlpha) T *= S(1) - a; else asum += w;
  }
  S bgw = mode == kAlpha ? T : S(1) - asum;
  for (int c = 0; c < C; ++c) img[c] += bgw * bg[c];
  *alpha_out = mode == kAlpha ? S(1) - T : asum;
  *depth_out = dep;
}

// Pass 1 of the backward for one pixel. Writes dalpha[j] (dL/dalpha_j times the estimator weight) and
// wf[j] (the feature weight times the estimator weight) for every filled slot; returns the background
// weight (dI/dbg).
template <typename S>
NS_HD S composite_backward_pixel(const SplatsView<S>& P, const S* feat, int C, const S* bg, const int* idx,
                                 const S* prob, int m, S u, S v, const Ray& ray, int mode, int estimator,
                                 const S* g_img, S g_alpha, S g_depth, S* dalpha, S* wf) {
  S g_bg = S(0);
  for (int c = 0; c < C; ++c) g_bg += g_img[c] * bg[c];
  int cnt = 0;
  while (cnt < m && idx[cnt] >= 0) ++cnt;
  if (mode == kAlpha) {
    S T = S(1);
    for (int j = 0; j < cnt; ++j) {
      bool clamped;
      int k = idx[j];
      dalpha[j] = T;  // T_j, consumed below
      T *= S(1) - splat_alpha(P.mu + 2 * k, P.con + 3 * k, P.amp[k], u, v, &clamped);
    }
    S t_end = T;
    S behind = t_end * (g_bg - g_alpha);
    for (int j = cnt - 1; j >= 0; --j) {
      int k = idx[j];
      bool clamped, on_plane;
      S dot;
      S a = splat_alpha(P.mu + 2 * k, P.con + 3 * k, P.amp[k], u, v, &clamped);
      S d = splat_depth(P.nrm + 3 * k, P.off[k], P.zc[k], ray, &on_plane, &dot);
      const S* f = feat + static_cast<int64_t>(k) * C;
      S cj = g_depth * d;
      for (int c = 0; c < C; ++c) cj += g_img[c] * f[c];
      S Tj = dalpha[j];
      S dl = Tj * cj - behind / (S(1) - a);
      S w = a * Tj;
      behind += w * cj;
      S est = estimator == kSampled ? S(1) : ht_weight(prob[j]);
      dalpha[j] = dl * est;
      wf[j] = w * est;
    }
    return t_end;
  }
  S asum = S(0);
  for (int j = 0; j < cnt; ++j) {
    int k = idx[j];
    bool clamped, on_plane;
    S dot;
    S a = splat_alpha(P.mu + 2 * k, P.con + 3 * k, P.amp[k], u, v, &clamped);
    S d = splat_depth(P.nrm + 3 * k, P.off[k], P.zc[k], ray, &on_plane, &dot);
    const S* f = feat + static_cast<int64_t>(k) * C;
    S inv = ht_weight(prob[j]);
    asum += a * inv;
    S cj = g_alpha - g_bg + g_depth * d;
    for (int c = 0; c < C; ++c) cj += g_img[c] * f[c];
    S est = estimator == kSampled ? S(1) : inv;
    dalpha[j] = cj * est;
    wf[j] = a * est;
  }
  return S(1) - asum;
}

// Per-point gradient of one (pixel, slot) entry: chains dL/dalpha (dla) and dL/ddepth (dld) through the
// kernel and the depth to the projected parameters (accumulated into g_*).
template <typename S>
NS_HD void splat_grad_entry(const SplatsView<S>& P, int k, S u, S v, const Ray& ray, S dla, S dld, S* g_mu, S* g_con,
                            S* g_amp, S* g_nrm, S* g_off, S* g_zc) {
  const S* mu = P.mu + 2 * k;
  const S* con = P.con + 3 * k;
  S dx = u - mu[0], dy = v - mu[1];
  S q = con[0] * dx * dx + S(2) * con[1] * dx * dy + con[2] * dy * dy;
  S e = sexp(S(-0.5) * q);
  S raw = P.amp[k] * e;
  if (!(raw > S(kAlphaMax)) && dla != S(0)) {
    *g_amp += dla * e;
    S a = dla * raw;
    g_mu[0] += a * (con[0] * dx + con[1] * dy);
    g_mu[1] += a * (con[1] * dx + con[2] * dy);
    g_con[0] += S(-0.5) * a * dx * dx;
    g_con[1] += -a * dx * dy;
    g_con[2] += S(-0.5) * a * dy * dy;
  }
  if (dld != S(0)) {
    bool on_plane;
    S dot;
    S t = splat_depth(P.nrm + 3 * k, P.off[k], P.zc[k], ray, &on_plane, &dot);
    if (on_plane) {
      S s = -dld * t / dot;
      g_nrm[0] += s * S(ray.x);
      g_nrm[1] += s * S(ray.y);
      g_nrm[2] += s;
      *g_off += dld / dot;
    } else {
      *g_zc += dld;
    }
  }
}

}  // namespace nsplat
