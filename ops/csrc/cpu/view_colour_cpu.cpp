// View-dependent colour on the CPU: the loops around core/view_colour.h (the model of nsplat/sh.py's view_colour,
// whose pure-PyTorch `view_colour_torch` is the reference, tests/test_sh.py). One task per point; the viewmat's
// gradient is summed in double over fixed blocks of kColourBlock points, then over the blocks in order: bitwise
// identical for any thread count.
#include "view_colour_cpu.h"

#include <algorithm>
#include <vector>

#include "../core/view_colour.h"

namespace nsplat {
namespace {

int threads() { return std::max(1, at::get_num_threads()); }

template <typename S>
void forward_impl(const at::Tensor& feat, const at::Tensor& means, const at::Tensor& viewmat, int degree,
                  at::Tensor& out) {
  const int64_t N = means.size(0), F = feat.size(1);
  const S* f = feat.data_ptr<S>();
  const S* M = means.data_ptr<S>();
  S c[3];
  centre(viewmat.data_ptr<S>(), c);
  S* o = out.data_ptr<S>();
#pragma omp parallel for num_threads(threads()) schedule(static)
  for (int64_t k = 0; k < N; ++k) colour_point(f + k * F, M + 3 * k, c, degree, o + 3 * k);
}

template <typename S>
void backward_impl(const at::Tensor& feat, const at::Tensor& means, const at::Tensor& viewmat, int degree,
                   const at::Tensor& g_out, at::Tensor& g_feat, at::Tensor& g_means, at::Tensor& g_view) {
  const int64_t N = means.size(0), F = feat.size(1);
  const S* f = feat.data_ptr<S>();
  const S* M = means.data_ptr<S>();
  const S* V = viewmat.data_ptr<S>();
  const S* g = g_out.data_ptr<S>();
  S c[3];
  centre(V, c);
  S* gf = g_feat.data_ptr<S>();
  S* gm = g_means.data_ptr<S>();
  const int64_t blocks = (N + kColourBlock - 1) / kColourBlock;
  std::vector<double> part(static_cast<size_t>(std::max<int64_t>(blocks, 1)) * 3, 0.0);
#pragma omp parallel for num_threads(threads()) schedule(static)
  for (int64_t blk = 0; blk < blocks; ++blk) {
    double* pc = part.data() + 3 * blk;
    for (int64_t k = blk * kColourBlock; k < std::min(N, (blk + 1) * kColourBlock); ++k) {
      colour_point_backward(f + k * F, M + 3 * k, c, degree, F, g + 3 * k, gf + k * F, gm + 3 * k);
      for (int i = 0; i < 3; ++i) pc[i] += static_cast<double>(gm[3 * k + i]);
    }
  }
  double gc[3] = {0, 0, 0};
  for (int64_t blk = 0; blk < blocks; ++blk)
    for (int i = 0; i < 3; ++i) gc[i] -= part[3 * blk + i];
  write_viewmat_grad(V, gc, g_view.data_ptr<S>());
}

void check_inputs(const std::vector<at::Tensor>& ts) {
  for (const auto& t : ts) {
    TORCH_CHECK(t.device().is_cpu(), "nsplat view colour (CPU): expected CPU tensors");
    TORCH_CHECK(t.is_contiguous(), "nsplat view colour (CPU): expected contiguous tensors");
    TORCH_CHECK(t.scalar_type() == ts[0].scalar_type(), "nsplat view colour (CPU): expected one float dtype");
  }
}

}  // namespace

at::Tensor view_colour_forward(at::Tensor feat, at::Tensor means, at::Tensor viewmat, int64_t degree) {
  check_inputs({feat, means, viewmat});
  TORCH_CHECK(degree >= 1 && degree <= 3, "nsplat view colour (CPU): degree 1..3");
  at::Tensor out = at::empty({means.size(0), 3}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_view_colour_forward", [&] {
    forward_impl<scalar_t>(feat, means, viewmat, static_cast<int>(degree), out);
  });
  return out;
}

std::vector<at::Tensor> view_colour_backward(at::Tensor feat, at::Tensor means, at::Tensor viewmat, int64_t degree,
                                             at::Tensor g_out) {
  check_inputs({feat, means, viewmat, g_out});
  TORCH_CHECK(degree >= 1 && degree <= 3, "nsplat view colour (CPU): degree 1..3");
  at::Tensor g_feat = at::empty_like(feat), g_means = at::empty_like(means), g_view = at::empty_like(viewmat);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "nsplat_view_colour_backward", [&] {
    backward_impl<scalar_t>(feat, means, viewmat, static_cast<int>(degree), g_out, g_feat, g_means, g_view);
  });
  return {g_feat, g_means, g_view};
}

}  // namespace nsplat
