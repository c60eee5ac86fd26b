// Python bindings of the CPU backend (the CUDA backend's are cuda/bindings.cpp): the shared API of
// ../api.h, defined in splat_cpu.cpp, plus the CPU-only counting sort, atomic-scatter backward,
// projection, view-dependent colour and the tiled render.
#include <torch/extension.h>

#include "../api.h"
#include "projection_cpu.h"
#include "scatter_cpu.h"
#include "tiled_cpu.h"
#include "view_colour_cpu.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("sample", &nsplat::sample, "Per-pixel SPS sample over the radix tree (CPU)");
  m.def("composite_forward", &nsplat::composite_forward, "Composite a given sample (CPU)");
  m.def("composite_backward_pixels", &nsplat::composite_backward_pixels, "Backward pass 1, per pixel (CPU)");
  m.def("composite_backward_points", &nsplat::composite_backward_points, "Backward pass 2, per point (CPU)");
  m.def("sampler_isa", &nsplat::sampler_isa, "The sampler's instruction set for a name ('auto' or one of sampler_isas())");
  m.def("sampler_isas", &nsplat::sampler_isas, "The sampler's instruction sets in this build");
  m.def("entries_by_point", &nsplat::entries_by_point, "Filled slots grouped by point, stable counting sort (CPU)");
  m.def("composite_backward_scatter", &nsplat::composite_backward_scatter,
        "Single-pass backward with atomic scatter (CPU, non-deterministic summation order)");
  m.def("project_forward", &nsplat::project_forward, "EWA projection of oriented surfels (CPU)");
  m.def("project_backward", &nsplat::project_backward, "Backward of project_forward (CPU)");
  m.def("view_colour_forward", &nsplat::view_colour_forward, "View-dependent SH colour (CPU)");
  m.def("render_tiled", &nsplat::render_tiled, "Every splat within a Mahalanobis radius, composited (CPU)");
  m.def("view_colour_backward", &nsplat::view_colour_backward, "Backward of view_colour_forward (CPU)");
}
