// The EWA projection of oriented surfels on the CPU: forward and hand-derived backward of the model of
// ops/projection.py (whose pure-PyTorch `project_torch` is the reference these kernels are tested against,
// tests/test_op_projection.py). One task per point: the point's frame once, then every camera in order, so
// the per-point gradients are summed over cameras in a fixed order; the per-camera gradients (viewmats, Ks)
// are summed over fixed blocks of kBlock points, then over the blocks in order. Both are bitwise identical for
// any thread count. The arithmetic runs in the tensors' dtype (as the reference does), the camera sums in double.
#include "projection_cpu.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace nsplat {
namespace {

constexpr int64_t kBlock = 512;   // points per block of the camera-gradient sums
constexpr int kCamGrads = 18;     // dR (9), dt (3), dK: k00 k01 cx k10 k11 cy (6)

int threads() { return std::max(1, at::get_num_threads()); }

// A point's camera-independent part: the unit normal and the scaled tangent axes (ops/projection.py).
template <typename S>
struct Frame {
  S v[3], norm, n[3], sign, a, b, t0[3], t1[3], s0, s1, T0w[3], T1w[3];
};

template <typename S>
Frame<S> point_frame(const S* normal, const S* scale) {
  Frame<S> f;
  for (int i = 0; i < 3; ++i) f.v[i] = normal[i];
  f.norm = std::sqrt(f.v[0] * f.v[0] + f.v[1] * f.v[1] + f.v[2] * f.v[2]);
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

template <typename S>
Camera<S> camera(const S* viewmat, const S* K) {
  Camera<S> c;
  for (int r = 0; r < 3; ++r) {
    for (int j = 0; j < 3; ++j) c.R[3 * r + j] = viewmat[4 * r + j];
    c.t[r] = viewmat[4 * r + 3];
  }
  for (int j = 0; j < 6; ++j) c.k[j] = K[j];
  return c;
}

// The inputs of a call: the surfels' arrays and the cameras.
template <typename S>
struct Scene {
  int64_t B, N;
  const S *M, *Nr, *Sc, *O;  // means, normals, scales, opacities
  std::vector<Camera<S>> cams;
};

template <typename S>
Scene<S> scene(const at::Tensor& means, const at::Tensor& normals, const at::Tensor& scales, const at::Tensor& opac,
               const at::Tensor& viewmats, const at::Tensor& Ks) {
  Scene<S> in{viewmats.size(0), means.size(0), means.data_ptr<S>(), normals.data_ptr<S>(), scales.data_ptr<S>(),
              opac.data_ptr<S>(), {}};
  for (int64_t b = 0; b < in.B; ++b)
    in.cams.push_back(camera(viewmats.data_ptr<S>() + 16 * b, Ks.data_ptr<S>() + 9 * b));
  return in;
}

// Every intermediate of one (camera, point) pair that the outputs and the backward need.
template <typename S>
struct Pair {
  S q[3], ncam[3], T0[3], T1[3];  // camera-space centre (zeroed when out of range), normal, tangent axes
  S z, zs, xn, yn, mx, my, a0, a1, b0, b1, j00, j01, j10, j11, detJ, s00, s01, s11, det, off, dets, half_tr;
  bool in_range, valid;
};

template <typename S>
inline void rotate(const S* R, const S* v, S* out) {
  for (int r = 0; r < 3; ++r) out[r] = R[3 * r] * v[0] + R[3 * r + 1] * v[1] + R[3 * r + 2] * v[2];
}

template <typename S>
Pair<S> pair(const Camera<S>& c, const Frame<S>& f, const S* mean, const ProjectSettings& st) {
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

template <typename S>
void forward_impl(const at::Tensor& means, const at::Tensor& normals, const at::Tensor& scales,
                  const at::Tensor& opac, const at::Tensor& viewmats, const at::Tensor& Ks, const ProjectSettings& st,
                  std::vector<at::Tensor>& out) {
  const Scene<S> in = scene<S>(means, normals, scales, opac, viewmats, Ks);
  const int64_t B = in.B, N = in.N;
  const S *M = in.M, *Nr = in.Nr, *Sc = in.Sc, *O = in.O;
  const std::vector<Camera<S>>& cams = in.cams;
  S* m2 = out[0].data_ptr<S>();
  S* con = out[1].data_ptr<S>();
  S* amp = out[2].data_ptr<S>();
  S* nc = out[3].data_ptr<S>();
  S* off = out[4].data_ptr<S>();
  S* dep = out[5].data_ptr<S>();
  S* sig = out[6].data_ptr<S>();
  bool* val = out[7].data_ptr<bool>();
  int8_t* haz = out[8].data_ptr<int8_t>();
#pragma omp parallel for num_threads(threads()) schedule(static)
  for (int64_t k = 0; k < N; ++k) {
    const Frame<S> f = point_frame(Nr + 3 * k, Sc + 2 * k);
    for (int64_t b = 0; b < B; ++b) {
      const Pair<S> p = pair(cams[b], f, M + 3 * k, st);
      const int64_t o = b * N + k;
      const bool v = p.valid;
      m2[2 * o] = v ? p.mx : S(0);
      m2[2 * o + 1] = v ? p.my : S(0);
      con[3 * o] = v ? p.s11 / p.dets : S(0);
      con[3 * o + 1] = v ? -p.s01 / p.dets : S(0);
      con[3 * o + 2] = v ? p.s00 / p.dets : S(0);
      amp[o] = v ? O[k] * std::abs(p.detJ) / std::sqrt(p.dets) : S(0);
      for (int r = 0; r < 3; ++r) nc[3 * o + r] = p.ncam[r];
      off[o] = p.off;
      dep[o] = p.z;
      const S disc = p.half_tr * p.half_tr - p.dets;
      sig[o] = v ? p.half_tr + std::sqrt(disc > S(0) ? disc : S(0)) : S(0);
      val[o] = v;
      const bool live = p.in_range && p.detJ != S(0);
      const bool huge = live && !(std::isfinite(p.det) && std::isfinite(p.detJ) && std::isfinite(p.mx) &&
                                  std::isfinite(p.my));
      const bool tiny = live && p.det > S(0) && p.det < S(1e-20);
      haz[o] = static_cast<int8_t>(huge ? 1 : tiny ? 2 : 0);
    }
  }
}

template <typename S>
void backward_impl(const at::Tensor& means, const at::Tensor& normals, const at::Tensor& scales,
                   const at::Tensor& opac, const at::Tensor& viewmats, const at::Tensor& Ks, const ProjectSettings& st,
                   const std::vector<at::Tensor>& g, std::vector<at::Tensor>& out) {
  const Scene<S> in = scene<S>(means, normals, scales, opac, viewmats, Ks);
  const int64_t B = in.B, N = in.N;
  const S *M = in.M, *Nr = in.Nr, *Sc = in.Sc, *O = in.O;
  const std::vector<Camera<S>>& cams = in.cams;
  const S* g_m2 = g[0].data_ptr<S>();
  const S* g_con = g[1].data_ptr<S>();
  const S* g_amp = g[2].data_ptr<S>();
  const S* g_nc = g[3].data_ptr<S>();
  const S* g_off = g[4].data_ptr<S>();
  const S* g_dep = g[5].data_ptr<S>();
  const S* g_sig = g[6].data_ptr<S>();
  S* dM = out[0].data_ptr<S>();
  S* dN = out[1].data_ptr<S>();
  S* dS = out[2].data_ptr<S>();
  S* dO = out[3].data_ptr<S>();
  const int64_t blocks = (N + kBlock - 1) / kBlock;
  std::vector<double> cam_part(static_cast<size_t>(std::max<int64_t>(blocks, 1)) * B * kCamGrads, 0.0);
#pragma omp parallel for num_threads(threads()) schedule(static)
  for (int64_t blk = 0; blk < blocks; ++blk) {
    double* part = cam_part.data() + blk * B * kCamGrads;
    for (int64_t k = blk * kBlock; k < std::min(N, (blk + 1) * kBlock); ++k) {
      const Frame<S> f = point_frame(Nr + 3 * k, Sc + 2 * k);
      const S* mean = M + 3 * k;
      S gm[3] = {0, 0, 0}, gn[3] = {0, 0, 0}, gT0w[3] = {0, 0, 0}, gT1w[3] = {0, 0, 0}, gop = 0;
      for (int64_t b = 0; b < B; ++b) {
        const Camera<S>& c = cams[b];
        const Pair<S> p = pair(c, f, mean, st);
        const int64_t o = b * N + k;
        const S k00 = c.k[0], k01 = c.k[1], k10 = c.k[3], k11 = c.k[4];
        S gk[6] = {0, 0, 0, 0, 0, 0};
        S gq[3] = {0, 0, 0}, gT0[3] = {0, 0, 0}, gT1[3] = {0, 0, 0}, gxn = 0, gyn = 0, gzs = 0;
        if (p.valid) {
          const S c0 = p.s11 / p.dets, c1 = -p.s01 / p.dets, c2 = p.s00 / p.dets;
          const S rs = std::sqrt(p.dets), adet = std::abs(p.detJ);
          const S amp = O[k] * adet / rs;
          S gs00 = g_con[3 * o + 2] / p.dets, gs01 = -g_con[3 * o + 1] / p.dets, gs11 = g_con[3 * o] / p.dets;
          S gdets = -(g_con[3 * o] * c0 + g_con[3 * o + 1] * c1 + g_con[3 * o + 2] * c2) / p.dets;
          const S ga = g_amp[o];
          gop += ga * adet / rs;
          const S gdetJ = ga * O[k] * (p.detJ > S(0) ? S(1) : S(-1)) / rs;
          gdets += -S(0.5) * ga * amp / p.dets;
          const S disc = p.half_tr * p.half_tr - p.dets;
          if (disc > S(0)) {
            const S r = std::sqrt(disc), gsg = g_sig[o];
            const S ght = gsg * (S(1) + p.half_tr / r);
            gdets += -S(0.5) * gsg / r;
            gs00 += S(0.5) * ght;
            gs11 += S(0.5) * ght;
          }
          // det = s00 s11 - s01^2 (dets = det on valid points)
          gs00 += gdets * p.s11;
          gs11 += gdets * p.s00;
          gs01 += -S(2) * gdets * p.s01;
          S gj00 = S(2) * p.j00 * gs00 + p.j10 * gs01 + p.j11 * gdetJ;
          S gj01 = S(2) * p.j01 * gs00 + p.j11 * gs01 - p.j10 * gdetJ;
          S gj10 = S(2) * p.j10 * gs11 + p.j00 * gs01 - p.j01 * gdetJ;
          S gj11 = S(2) * p.j11 * gs11 + p.j01 * gs01 + p.j00 * gdetJ;
          gk[0] += gj00 * p.a0 + gj01 * p.b0;
          gk[1] += gj00 * p.a1 + gj01 * p.b1;
          gk[3] += gj10 * p.a0 + gj11 * p.b0;
          gk[4] += gj10 * p.a1 + gj11 * p.b1;
          const S ga0 = k00 * gj00 + k10 * gj10, ga1 = k01 * gj00 + k11 * gj10;
          const S gb0 = k00 * gj01 + k10 * gj11, gb1 = k01 * gj01 + k11 * gj11;
          const S gmx = g_m2[2 * o], gmy = g_m2[2 * o + 1];
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
        const S go = g_off[o];
        for (int r = 0; r < 3; ++r) {
          gncam[r] = g_nc[3 * o + r] + go * p.q[r];
          gq[r] += go * p.ncam[r];
        }
        gq[0] += gxn / p.zs;
        gq[1] += gyn / p.zs;
        gzs += -(gxn * p.xn + gyn * p.yn) / p.zs;
        if (!p.in_range) {  // the zeroed q, T0, T1 pass no gradient; zs = 1 is constant
          for (int r = 0; r < 3; ++r) gq[r] = gT0[r] = gT1[r] = S(0);
          gzs = S(0);
        }
        gq[2] += gzs + g_dep[o];  // z = q_z feeds zs and the depth output
        // q = R mean + t, n_c = R n, T0 = R T0w, T1 = R T1w
        double* cp = part + b * kCamGrads;
        for (int r = 0; r < 3; ++r) {
          for (int j = 0; j < 3; ++j) {
            cp[3 * r + j] += static_cast<double>(gq[r] * mean[j] + gncam[r] * f.n[j] + gT0[r] * f.T0w[j] +
                                                 gT1[r] * f.T1w[j]);
          }
          cp[9 + r] += static_cast<double>(gq[r]);
        }
        for (int j = 0; j < 6; ++j) cp[12 + j] += static_cast<double>(gk[j]);
        for (int j = 0; j < 3; ++j) {
          const S* R = c.R;
          gm[j] += R[j] * gq[0] + R[3 + j] * gq[1] + R[6 + j] * gq[2];
          gn[j] += R[j] * gncam[0] + R[3 + j] * gncam[1] + R[6 + j] * gncam[2];
          gT0w[j] += R[j] * gT0[0] + R[3 + j] * gT0[1] + R[6 + j] * gT0[2];
          gT1w[j] += R[j] * gT1[0] + R[3 + j] * gT1[1] + R[6 + j] * gT1[2];
        }
      }
      // T0w = t0 s0, T1w = t1 s1; the tangent frame of the unit normal; the normalisation
      S gt0[3], gt1[3];
      for (int j = 0; j < 3; ++j) {
        gt0[j] = gT0w[j] * f.s0;
        gt1[j] = gT1w[j] * f.s1;
      }
      dS[2 * k] = gT0w[0] * f.t0[0] + gT0w[1] * f.t0[1] + gT0w[2] * f.t0[2];
      dS[2 * k + 1] = gT1w[0] * f.t1[0] + gT1w[1] * f.t1[1] + gT1w[2] * f.t1[2];
      const S x = f.n[0], y = f.n[1], sg = f.sign, a = f.a;
      S gx = gt0[0] * S(2) * sg * x * a - gt0[2] * sg;
      S gy = gt1[1] * S(2) * y * a - gt1[2];
      S gb = gt0[1] * sg + gt1[0];
      S ga = gt0[0] * sg * x * x + gt1[1] * y * y;
      gx += gb * y * a;
      gy += gb * x * a;
      ga += gb * x * y;
      const S gz = ga * a * a;  // a = -1 / (sign + z)
      const S gh[3] = {gn[0] + gx, gn[1] + gy, gn[2] + gz};
      const S dot = f.n[0] * gh[0] + f.n[1] * gh[1] + f.n[2] * gh[2];
      for (int j = 0; j < 3; ++j) {
        dN[3 * k + j] = (gh[j] - f.n[j] * dot) / f.norm;
        dM[3 * k + j] = gm[j];
      }
      dO[k] = gop;
    }
  }
  S* dV = out[4].data_ptr<S>();
  S* dK = out[5].data_ptr<S>();
  for (int64_t b = 0; b < B; ++b) {
    double sum[kCamGrads] = {0};
    for (int64_t blk = 0; blk < blocks; ++blk)
      for (int j = 0; j < kCamGrads; ++j) sum[j] += cam_part[(blk * B + b) * kCamGrads + j];
    S* v = dV + 16 * b;
    for (int r = 0; r < 3; ++r) {
      for (int j = 0; j < 3; ++j) v[4 * r + j] = static_cast<S>(sum[3 * r + j]);
      v[4 * r + 3] = static_cast<S>(sum[9 + r]);
    }
    for (int j = 12; j < 16; ++j) v[j] = S(0);
    S* kk = dK + 9 * b;
    for (int j = 0; j < 6; ++j) kk[j] = static_cast<S>(sum[12 + j]);
    for (int j = 6; j < 9; ++j) kk[j] = S(0);
  }
}

void check_inputs(const std::vector<at::Tensor>& ts) {
  for (const auto& t : ts) {
    TORCH_CHECK(t.device().is_cpu(), "nsplat projection (CPU): expected CPU tensors");
    TORCH_CHECK(t.is_contiguous(), "nsplat projection (CPU): expected contiguous tensors");
    TORCH_CHECK(t.scalar_type() == ts[0].scalar_type(), "nsplat projection (CPU): expected one float dtype");
  }
}

}  // namespace

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                        at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                        bool backface_cull) {
  check_inputs({means, normals, scales, opac, viewmats, Ks});
  const int64_t B = viewmats.size(0), N = means.size(0);
  const auto o = means.options();
  std::vector<at::Tensor> out = {at::empty({B, N, 2}, o), at::empty({B, N, 3}, o), at::empty({B, N}, o),
                                 at::empty({B, N, 3}, o), at::empty({B, N}, o),    at::empty({B, N}, o),
                                 at::empty({B, N}, o),    at::empty({B, N}, o.dtype(at::kBool)),
                                 at::empty({B, N}, o.dtype(at::kChar))};
  const ProjectSettings st{near, far, lowpass, backface_cull};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_project_forward", [&] {
    forward_impl<scalar_t>(means, normals, scales, opac, viewmats, Ks, st, out);
  });
  return out;
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor normals, at::Tensor scales, at::Tensor opac,
                                         at::Tensor viewmats, at::Tensor Ks, double near, double far, double lowpass,
                                         bool backface_cull, at::Tensor g_means2d, at::Tensor g_conics,
                                         at::Tensor g_amps, at::Tensor g_normals_cam, at::Tensor g_plane_offsets,
                                         at::Tensor g_depths, at::Tensor g_sigma2) {
  const std::vector<at::Tensor> g = {g_means2d, g_conics, g_amps, g_normals_cam, g_plane_offsets, g_depths, g_sigma2};
  std::vector<at::Tensor> all = {means, normals, scales, opac, viewmats, Ks};
  all.insert(all.end(), g.begin(), g.end());
  check_inputs(all);
  std::vector<at::Tensor> out = {at::empty_like(means), at::empty_like(normals), at::empty_like(scales),
                                 at::empty_like(opac),  at::empty_like(viewmats), at::empty_like(Ks)};
  const ProjectSettings st{near, far, lowpass, backface_cull};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_project_backward", [&] {
    backward_impl<scalar_t>(means, normals, scales, opac, viewmats, Ks, st, g, out);
  });
  return out;
}

}  // namespace nsplat
