// The EWA projection of oriented surfels, one (camera, point) pair at a time: forward and hand-derived backward
// of the model of ops/projection.py (whose pure-PyTorch `project_torch` is the reference, tests/test_op_projection.py
// and tests/test_op_cuda.py). Host and device code: the CPU backend (cpu/projection_cpu.cpp) and the CUDA backend
// (cuda/projection_cuda.cu) run these functions in their own loops. The arithmetic runs in the working type S
// (float or double), as the reference does.
//
// Per point: `point_frame` (unit normal, tangent frame, scaled axes). Per pair: `pair` (every intermediate),
// `write_pair` (the forward's outputs), `pair_backward` (the pair's gradient: added to the point's accumulators,
// and its contribution to the camera's 18 gradients returned). Per point again: `finish_point` (the gradients of
// the normal, the scales, the mean and the opacity from the accumulators). Summing the camera contributions over
// the points is the backends' business (both: fixed blocks of kProjectBlock points, then the blocks in order).
#pragma once
#include "common.h"

namespace nsplat {

constexpr int64_t kProjectBlock = 512;  // points per block of the camera-gradient sums
constexpr int kCamGrads = 18;           // dR (9, row-major), dt (3), dK: k00 k01 cx k10 k11 cy (6)

struct ProjectSettings {
  double near, far, lowpass;
  bool backface_cull;
};

// A point's camera-independent part: the unit normal and the scaled tangent axes.
template <typename S>
struct Frame {
  S v[3], norm, n[3], sign, a, b, t0[3], t1[3], s0, s1, T0w[3], T1w[3];
};

template <typename S>
NS_HD Frame<S> point_frame(const S* normal, const S* scale) {
  Frame<S> f;
  for (int i = 0; i < 3; ++i) f.v[i] = normal[i];
  f.norm = ssqrt(f.v[0] * f.v[0] + f.v[1] * f.v[1] + f.v[2] * f.v[2]);
  for (int i = 0; i < 3; ++i) f.n[i] = f.v[i] / f.norm;
  const S x = f.n[0], y = f.n[1], z = f.n[2];
  f.sign = z >= S(0) ? S(1) : S(-1);
  f.a = S(-1) / (f.sign + z);
  f.b = x * y * f.a;
  f.t0[0] = S(1) + f.sign * x * x * f.a;
  f.t0[1] = f.sign * f.b;
  f.t0[2] = -f.sign * x;
  f.t1[0] = f.b;
  f.t1[1] = f.sign + y * y * f.a;
  f.t1[2] = -y;
  f.s0 = scale[0];
  f.s1 = scale[1];
  for (int i = 0; i < 3; ++i) {
    f.T0w[i] = f.t0[i] * f.s0;
    f.T1w[i] = f.t1[i] * f.s1;
  }
  return f;
}

// One camera: rotation R (row-major), translation t, intrinsics k00 k01 cx k10 k11 cy.
template <typename S>
struct Camera {
  S R[9], t[3], k[6];
};

// The camera of a world-to-camera matrix `viewmat [4,4]` and intrinsics `K [3,3]` (row-major).
template <typename S>
NS_HD Camera<S> load_camera(const S* viewmat, const S* K) {
  Camera<S> c;
  for (int r = 0; r < 3; ++r) {
    for (int j = 0; j < 3; ++j) c.R[3 * r + j] = viewmat[4 * r + j];
    c.t[r] = viewmat[4 * r + 3];
  }
  for (int j = 0; j < 6; ++j) c.k[j] = K[j];
  return c;
}

// Every intermediate of one (camera, point) pair that the outputs and the backward need.
template <typename S>
struct Pair {
  S q[3], ncam[3], T0[3], T1[3];  // camera-space centre (zeroed when out of range), normal, tangent axes
  S z, zs, xn, yn, mx, my, a0, a1, b0, b1, j00, j01, j10, j11, detJ, s00, s01, s11, det, off, dets, half_tr;
  bool in_range, valid;
};

template <typename S>
NS_HD void rotate(const S* R, const S* v, S* out) {
  for (int r = 0; r < 3; ++r) out[r] = R[3 * r] * v[0] + R[3 * r + 1] * v[1] + R[3 * r + 2] * v[2];
}

template <typename S>
NS_HD Pair<S> pair(const Camera<S>& c, const Frame<S>& f, const S* mean, const ProjectSettings& st) {
  Pair<S> p;
  rotate(c.R, mean, p.q);
  for (int r = 0; r < 3; ++r) p.q[r] = p.q[r] + c.t[r];
  rotate(c.R, f.n, p.ncam);
  rotate(c.R, f.T0w, p.T0);
  rotate(c.R, f.T1w, p.T1);
  p.z = p.q[2];
  p.in_range = p.z >= S(st.near) && p.z <= S(st.far);
  p.zs = p.in_range ? p.z : S(1);
  if (!p.in_range)
    for (int r = 0; r < 3; ++r) p.q[r] = p.T0[r] = p.T1[r] = S(0);
  const S k00 = c.k[0], k01 = c.k[1], cx = c.k[2], k10 = c.k[3], k11 = c.k[4], cy = c.k[5];
  p.xn = p.q[0] / p.zs;
  p.yn = p.q[1] / p.zs;
  p.mx = k00 * p.xn + k01 * p.yn + cx;
  p.my = k10 * p.xn + k11 * p.yn + cy;
  p.a0 = (p.T0[0] - p.xn * p.T0[2]) / p.zs;
  p.a1 = (p.T0[1] - p.yn * p.T0[2]) / p.zs;
  p.b0 = (p.T1[0] - p.xn * p.T1[2]) / p.zs;
  p.b1 = (p.T1[1] - p.yn * p.T1[2]) / p.zs;
  p.j00 = k00 * p.a0 + k01 * p.a1;
  p.j01 = k00 * p.b0 + k01 * p.b1;
  p.j10 = k10 * p.a0 + k11 * p.a1;
  p.j11 = k10 * p.b0 + k11 * p.b1;
  p.detJ = p.j00 * p.j11 - p.j01 * p.j10;
  const S lp = S(st.lowpass);
  p.s00 = (p.j00 * p.j00 + p.j01 * p.j01) + lp;
  p.s01 = p.j00 * p.j10 + p.j01 * p.j11;
  p.s11 = (p.j10 * p.j10 + p.j11 * p.j11) + lp;
  p.det = p.s00 * p.s11 - p.s01 * p.s01;
  p.off = p.ncam[0] * p.q[0] + p.ncam[1] * p.q[1] + p.ncam[2] * p.q[2];
  p.valid = p.in_range && p.detJ != S(0) && p.det > S(0) && (!st.backface_cull || p.off < S(0));
  p.dets = p.valid ? p.det : S(1);
  p.half_tr = S(0.5) * (p.s00 + p.s11);
  return p;
}

// The forward's output arrays ([B,N,...] flattened; `o` = b N + k indexes a pair).
template <typename S>
struct ProjectOutputs {
  S *means2d, *conics, *amps, *normals_cam, *plane_offsets, *depths, *sigma2;
  bool* valid;
  int8_t* hazard;  // 1: a visible splat overflows the dtype, 2: its det Sigma lies in (0, 1e-20) px^4
};

template <typename S>
NS_HD void write_pair(const Pair<S>& p, S opacity, int64_t o, const ProjectOutputs<S>& out) {
  const bool v = p.valid;
  out.means2d[2 * o] = v ? p.mx : S(0);
  out.means2d[2 * o + 1] = v ? p.my : S(0);
  out.conics[3 * o] = v ? p.s11 / p.dets : S(0);
  out.conics[3 * o + 1] = v ? -p.s01 / p.dets : S(0);
  out.conics[3 * o + 2] = v ? p.s00 / p.dets : S(0);
  out.amps[o] = v ? opacity * sabs(p.detJ) / ssqrt(p.dets) : S(0);
  for (int r = 0; r < 3; ++r) out.normals_cam[3 * o + r] = p.ncam[r];
  out.plane_offsets[o] = p.off;
  out.depths[o] = p.z;
  const S disc = p.half_tr * p.half_tr - p.dets;
  out.sigma2[o] = v ? p.half_tr + ssqrt(disc > S(0) ? disc : S(0)) : S(0);
  out.valid[o] = v;
  const bool live = p.in_range && p.detJ != S(0);
  const bool huge = live && !(sfinite(p.det) && sfinite(p.detJ) && sfinite(p.mx) && sfinite(p.my));
  const bool tiny = live && p.det > S(0) && p.det < S(1e-20);
  out.hazard[o] = static_cast<int8_t>(huge ? 1 : tiny ? 2 : 0);
}

// The gradients of the forward's first seven outputs ([B,N,...] flattened, as ProjectOutputs).
template <typename S>
struct ProjectGrads {
  const S *means2d, *conics, *amps, *normals_cam, *plane_offsets, *depths, *sigma2;
};

// A point's gradient accumulators over its cameras: mean, unit normal, scaled tangent axes, opacity.
template <typename S>
struct PointGrad {
  S m[3] = {0, 0, 0}, n[3] = {0, 0, 0}, T0w[3] = {0, 0, 0}, T1w[3] = {0, 0, 0}, opacity = 0;
};

// The backward of pair (c, f, mean) = p with the gradients g at o: adds its share to the point's accumulators
// `acc` and writes its contribution to the camera's gradients into `cam[kCamGrads]`.
template <typename S>
NS_HD void pair_backward(const Camera<S>& c, const Frame<S>& f, const S* mean, S opacity, const Pair<S>& p,
                         const ProjectGrads<S>& g, int64_t o, PointGrad<S>& acc, S* cam) {
  const S k00 = c.k[0], k01 = c.k[1], k10 = c.k[3], k11 = c.k[4];
  S gk[6] = {0, 0, 0, 0, 0, 0};
  S gq[3] = {0, 0, 0}, gT0[3] = {0, 0, 0}, gT1[3] = {0, 0, 0}, gxn = 0, gyn = 0, gzs = 0;
  if (p.valid) {
    const S* gc = g.conics + 3 * o;
    const S c0 = p.s11 / p.dets, c1 = -p.s01 / p.dets, c2 = p.s00 / p.dets;
    const S rs = ssqrt(p.dets), adet = sabs(p.detJ);
    const S amp = opacity * adet / rs;
    S gs00 = gc[2] / p.dets, gs01 = -gc[1] / p.dets, gs11 = gc[0] / p.dets;
    S gdets = -(gc[0] * c0 + gc[1] * c1 + gc[2] * c2) / p.dets;
    const S ga = g.amps[o];
    acc.opacity += ga * adet / rs;
    const S gdetJ = ga * opacity * (p.detJ > S(0) ? S(1) : S(-1)) / rs;
    gdets += -S(0.5) * ga * amp / p.dets;
    const S disc = p.half_tr * p.half_tr - p.dets;
    if (disc > S(0)) {
      const S r = ssqrt(disc), gsg = g.sigma2[o];
      const S ght = gsg * (S(1) + p.half_tr / r);
      gdets += -S(0.5) * gsg / r;
      gs00 += S(0.5) * ght;
      gs11 += S(0.5) * ght;
    }
    // det = s00 s11 - s01^2 (dets = det on valid points)
    gs00 += gdets * p.s11;
    gs11 += gdets * p.s00;
    gs01 += -S(2) * gdets * p.s01;
    const S gj00 = S(2) * p.j00 * gs00 + p.j10 * gs01 + p.j11 * gdetJ;
    const S gj01 = S(2) * p.j01 * gs00 + p.j11 * gs01 - p.j10 * gdetJ;
    const S gj10 = S(2) * p.j10 * gs11 + p.j00 * gs01 - p.j01 * gdetJ;
    const S gj11 = S(2) * p.j11 * gs11 + p.j01 * gs01 + p.j00 * gdetJ;
    gk[0] += gj00 * p.a0 + gj01 * p.b0;
    gk[1] += gj00 * p.a1 + gj01 * p.b1;
    gk[3] += gj10 * p.a0 + gj11 * p.b0;
    gk[4] += gj10 * p.a1 + gj11 * p.b1;
    const S ga0 = k00 * gj00 + k10 * gj10, ga1 = k01 * gj00 + k11 * gj10;
    const S gb0 = k00 * gj01 + k10 * gj11, gb1 = k01 * gj01 + k11 * gj11;
    const S gmx = g.means2d[2 * o], gmy = g.means2d[2 * o + 1];
    gk[0] += gmx * p.xn;
    gk[1] += gmx * p.yn;
    gk[2] += gmx;
    gk[3] += gmy * p.xn;
    gk[4] += gmy * p.yn;
    gk[5] += gmy;
    gxn += k00 * gmx + k10 * gmy;
    gyn += k01 * gmx + k11 * gmy;
    // a0 = (T0x - xn T0z) / zs, a1 = (T0y - yn T0z) / zs, b0, b1 likewise with T1
    gT0[0] += ga0 / p.zs;
    gT0[1] += ga1 / p.zs;
    gT0[2] += -(ga0 * p.xn + ga1 * p.yn) / p.zs;
    gT1[0] += gb0 / p.zs;
    gT1[1] += gb1 / p.zs;
    gT1[2] += -(gb0 * p.xn + gb1 * p.yn) / p.zs;
    gxn += -(ga0 * p.T0[2] + gb0 * p.T1[2]) / p.zs;
    gyn += -(ga1 * p.T0[2] + gb1 * p.T1[2]) / p.zs;
    gzs += -(ga0 * p.a0 + ga1 * p.a1 + gb0 * p.b0 + gb1 * p.b1) / p.zs;
  }
  // plane offset n_c . q (q zeroed out of range), x_n = q_x / zs, y_n = q_y / zs
  S gncam[3];
  const S go = g.plane_offsets[o];
  for (int r = 0; r < 3; ++r) {
    gncam[r] = g.normals_cam[3 * o + r] + go * p.q[r];
    gq[r] += go * p.ncam[r];
  }
  gq[0] += gxn / p.zs;
  gq[1] += gyn / p.zs;
  gzs += -(gxn * p.xn + gyn * p.yn) / p.zs;
  if (!p.in_range) {  // the zeroed q, T0, T1 pass no gradient; zs = 1 is constant
    for (int r = 0; r < 3; ++r) gq[r] = gT0[r] = gT1[r] = S(0);
    gzs = S(0);
  }
  gq[2] += gzs + g.depths[o];  // z = q_z feeds zs and the depth output
  // q = R mean + t, n_c = R n, T0 = R T0w, T1 = R T1w
  for (int r = 0; r < 3; ++r) {
    for (int j = 0; j < 3; ++j)
      cam[3 * r + j] = gq[r] * mean[j] + gncam[r] * f.n[j] + gT0[r] * f.T0w[j] + gT1[r] * f.T1w[j];
    cam[9 + r] = gq[r];
  }
  for (int j = 0; j < 6; ++j) cam[12 + j] = gk[j];
  const S* R = c.R;
  for (int j = 0; j < 3; ++j) {
    acc.m[j] += R[j] * gq[0] + R[3 + j] * gq[1] + R[6 + j] * gq[2];
    acc.n[j] += R[j] * gncam[0] + R[3 + j] * gncam[1] + R[6 + j] * gncam[2];
    acc.T0w[j] += R[j] * gT0[0] + R[3 + j] * gT0[1] + R[6 + j] * gT0[2];
    acc.T1w[j] += R[j] * gT1[0] + R[3 + j] * gT1[1] + R[6 + j] * gT1[2];
  }
}

// Point k's gradients from its accumulators: dM [3], dN [3], dS [2], dO [1] at k.
template <typename S>
NS_HD void finish_point(const Frame<S>& f, const PointGrad<S>& acc, int64_t k, S* dM, S* dN, S* dS, S* dO) {
  // T0w = t0 s0, T1w = t1 s1; the tangent frame of the unit normal; the normalisation
  S gt0[3], gt1[3];
  for (int j = 0; j < 3; ++j) {
    gt0[j] = acc.T0w[j] * f.s0;
    gt1[j] = acc.T1w[j] * f.s1;
  }
  dS[2 * k] = acc.T0w[0] * f.t0[0] + acc.T0w[1] * f.t0[1] + acc.T0w[2] * f.t0[2];
  dS[2 * k + 1] = acc.T1w[0] * f.t1[0] + acc.T1w[1] * f.t1[1] + acc.T1w[2] * f.t1[2];
  const S x = f.n[0], y = f.n[1], sg = f.sign, a = f.a;
  S gx = gt0[0] * S(2) * sg * x * a - gt0[2] * sg;
  S gy = gt1[1] * S(2) * y * a - gt1[2];
  S gb = gt0[1] * sg + gt1[0];
  S ga = gt0[0] * sg * x * x + gt1[1] * y * y;
  gx += gb * y * a;
  gy += gb * x * a;
  ga += gb * x * y;
  const S gz = ga * a * a;  // a = -1 / (sign + z)
  const S gh[3] = {acc.n[0] + gx, acc.n[1] + gy, acc.n[2] + gz};
  const S dot = f.n[0] * gh[0] + f.n[1] * gh[1] + f.n[2] * gh[2];
  for (int j = 0; j < 3; ++j) {
    dN[3 * k + j] = (gh[j] - f.n[j] * dot) / f.norm;
    dM[3 * k + j] = acc.m[j];
  }
  dO[k] = acc.opacity;
}

// The camera's gradients from their 18 sums: dV [16] (row 3 zero) and dK [9] (row 2 zero) of one camera.
template <typename S>
NS_HD void write_camera_grads(const double* sum, S* dV, S* dK) {
  for (int r = 0; r < 3; ++r) {
    for (int j = 0; j < 3; ++j) dV[4 * r + j] = static_cast<S>(sum[3 * r + j]);
    dV[4 * r + 3] = static_cast<S>(sum[9 + r]);
  }
  for (int j = 12; j < 16; ++j) dV[j] = S(0);
  for (int j = 0; j < 6; ++j) dK[j] = static_cast<S>(sum[12 + j]);
  for (int j = 6; j < 9; ++j) dK[j] = S(0);
}

}  // namespace nsplat
