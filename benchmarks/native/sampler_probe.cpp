// Benchmark-only probe of the CPU sampler (benchmarks/sampler_real.py): runs the op's own per-pixel driver
// on one camera and returns, per pixel, the exact kernel evaluations and the tree nodes visited (bounds
// computed), which the op's `work` output does not carry. Includes the CPU backend source so that the probe
// runs exactly the op's code; the backend's Python bindings are compiled into an unused function.
#include <torch/extension.h>

#include <vector>

std::vector<at::Tensor> probe(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                              at::Tensor off, at::Tensor zc, at::Tensor Ks, int64_t width, int64_t height,
                              int64_t samples, double eps, int64_t seed, int64_t order, double tol);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def("probe", &probe, "sampler work counters of camera 0"); }

#undef PYBIND11_MODULE
#define PYBIND11_MODULE(name, variable) [[maybe_unused]] static void nsplat_unused_bindings(pybind11::module_& variable)
#include "../../ops/csrc/cpu/splat_cpu.cpp"

std::vector<at::Tensor> probe(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                              at::Tensor off, at::Tensor zc, at::Tensor Ks, int64_t width, int64_t height,
                              int64_t samples, double eps, int64_t seed, int64_t order, double tol) {
  using namespace nsplat;
  TORCH_CHECK(mu.scalar_type() == at::kFloat, "probe: float32 inputs");
  const int64_t B = amp.size(0), N = amp.size(1), P = width * height, m = samples;
  at::Tensor indices = at::empty({B, height, width, m}, mu.options().dtype(at::kInt));
  at::Tensor probs = at::empty({B, height, width, m}, mu.options());
  at::Tensor total = at::empty({B, height, width, 1}, mu.options());
  at::Tensor work = at::empty({B, height, width, 1}, mu.options().dtype(at::kInt));
  at::Tensor nodes = at::zeros({B, height, width, 1}, mu.options().dtype(at::kInt));
  at::Tensor Kd = Ks.to(at::kDouble).contiguous();
  SamplerCounters counters{nodes.data_ptr<int>()};
  sample_impl<float>(mu, con, amp, sig2, nrm, off, zc, Kd, width, height, m, std::log(eps), seed,
                     static_cast<int>(order), tol, kThreshold, false, indices, probs, total, work, &counters);
  (void)N;
  (void)P;
  return {indices, probs, total, work, nodes};
}
