// Benchmark-only probe of the CPU sampler (benchmarks/sampler_real.py): runs the op's own per-pixel driver
// on one camera and returns, per pixel, the exact kernel evaluations and the tree nodes visited (bounds
// computed), which the op's `work` output does not carry; and times the sampler's inner loop alone
// (`offer_bench`: offer_point, i.e. one exact kernel evaluation with its draw, rejection test and heap update). Includes the CPU backend source so that the probe
// runs exactly the op's code; the backend's Python bindings are compiled into an unused function.
#include <torch/extension.h>

#include <ctime>
#include <vector>

std::vector<at::Tensor> probe(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor nrm,
                              at::Tensor off, at::Tensor zc, at::Tensor Ks, int64_t width, int64_t height,
                              int64_t samples, double eps, int64_t seed, int64_t order, double tol);

std::vector<double> offer_bench(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor pixels,
                                int64_t width, int64_t samples, int64_t seed, double min_lambda, int64_t repeats);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("probe", &probe, "sampler work counters of camera 0");
  m.def("offer_bench", &offer_bench, "seconds and evaluations of the inner loop alone");
}

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

// The inner loop alone: for each pixel of `pixels` (flat indices), the points of camera 0 with lambda > min_lambda
// at the pixel centre (collected untimed, in the tree's Morton order, as a pixel's search visits its groups)
// are offered to a fresh sample of size `samples` with the pixel's own draws; the offers are timed (process CPU
// time, the fastest of `repeats` passes). Returns {seconds, offers}.
std::vector<double> offer_bench(at::Tensor mu, at::Tensor con, at::Tensor amp, at::Tensor sig2, at::Tensor pixels,
                                int64_t width, int64_t samples, int64_t seed, double min_lambda, int64_t repeats) {
  using namespace nsplat;
  TORCH_CHECK(mu.scalar_type() == at::kFloat, "offer_bench: float32 inputs");
  const int64_t N = amp.size(1);
  CpuTree tree;
  build_tree<float>(tree, mu.data_ptr<float>(), con.data_ptr<float>(), amp.data_ptr<float>(), sig2.data_ptr<float>(),
                    N, 8, 1e-3);
  const TreeView tv = tree.view();
  const int64_t* px = pixels.data_ptr<int64_t>();
  const int64_t np = pixels.numel();
  std::vector<std::vector<int>> lists(np);
  for (int64_t i = 0; i < np; ++i) {
    const double u = double(px[i] % width) + 0.5, v = double(px[i] / width) + 0.5;
    for (int s = 0; s < tv.n; ++s)
      if (log_size(tv.mu + 2 * s, tv.con + 3 * s, tv.logA[s], u, v) > std::log(min_lambda)) lists[i].push_back(s);
  }
  std::vector<double> key(samples);
  std::vector<int> idx(samples);
  double best = INFINITY, offers = 0.0, sink = 0.0;
  for (int64_t r = 0; r < repeats; ++r) {
    offers = 0.0;
    std::clock_t c0 = std::clock();
    for (int64_t i = 0; i < np; ++i) {
      const double u = double(px[i] % width) + 0.5, v = double(px[i] / width) + 0.5;
      const Draw draw = pixel_draw(static_cast<uint64_t>(seed), 0, px[i], width, false);
      PixelState S = pixel_state(key.data(), idx.data(), static_cast<int>(samples), std::log(0.01));
      for (int s : lists[i]) offer_point(tv, s, u, v, draw, S);
      offers += S.evaluated;
      sink += S.visited;
    }
    best = std::min(best, double(std::clock() - c0) / CLOCKS_PER_SEC);
  }
  TORCH_CHECK(sink >= 0.0, "offer_bench: negative mass");
  return {best, offers};
}
