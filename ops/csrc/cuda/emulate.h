// Host emulation of the few CUDA constructs splat_cuda.cu uses, for testing its launch code without a GPU.
//
// Included by splat_cuda.cu when NSPLAT_CUDA_EMULATE is defined (emulate.cpp). A launch runs the kernel body
// once per (block, thread) of its grid, sequentially, with blockIdx/threadIdx/blockDim/gridDim set as on the
// device. This is faithful for splat_cuda.cu's kernels because none of them uses shared memory, barriers or
// warp primitives, and every cross-thread interaction (propagate_up's arrival counter) is correct under any
// interleaving, so also under the sequential one. What the emulation cannot show: device code generation,
// the device memory model, real concurrency, and cub (replaced by std algorithms in splat_cuda.cu).
#pragma once
#if !defined(NSPLAT_CUDA_EMULATE) || defined(__CUDACC__)
#error "emulate.h is only for the host emulation build (NSPLAT_CUDA_EMULATE, host compiler)"
#endif

#include <c10/core/Device.h>

#include <cstdint>

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __launch_bounds__(...)
#define __maxnreg__(...)

namespace nsplat {
namespace emu {

struct Dim3 {
  unsigned int x = 0, y = 0, z = 0;
};

// The emulated launch's current indices (one launch at a time: launches are sequential on the host).
inline Dim3 blockIdx, threadIdx, blockDim, gridDim;

using Stream = int;
inline Stream current_stream() { return 0; }

struct DeviceGuard {
  explicit DeviceGuard(const c10::Device&) {}
};

// Kernel launches and cub primitives (each one or more device launches) so far, for the tests.
inline int64_t launch_count = 0;

template <typename F>
void launch(unsigned int grid, unsigned int block, F&& body) {
  ++launch_count;
  gridDim.x = grid;
  blockDim.x = block;
  for (unsigned int b = 0; b < grid; ++b) {
    blockIdx.x = b;
    for (unsigned int t = 0; t < block; ++t) {
      threadIdx.x = t;
      body();
    }
  }
}

}  // namespace emu

using emu::blockDim;
using emu::blockIdx;
using emu::gridDim;
using emu::threadIdx;

}  // namespace nsplat

#define NS_LAUNCH(kernel, grid, block, stream, ...) \
  ::nsplat::emu::launch((grid), (block), [&] { kernel(__VA_ARGS__); })
#define NS_LAUNCH_CHECK() ((void)0)
