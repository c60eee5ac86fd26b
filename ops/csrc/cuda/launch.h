// Launch helpers shared by the CUDA backend's kernel files (splat_cuda.cu, projection_cuda.cu): the launch
// macro, the stream and device guard, raw buffers, grid-stride loops, and cub's sort and scan. With
// NSPLAT_CUDA_EMULATE (emulate.cpp) they map onto the host emulation of emulate.h, where cub is replaced by
// std algorithms.
#pragma once
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>

#include <algorithm>
#include <atomic>
#include <vector>

#if defined(NSPLAT_CUDA_EMULATE)
#include "emulate.h"
#else
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

// Kernel launch on a stream; emulate.h gives the host emulation's version.
#define NS_LAUNCH(kernel, grid, block, stream, ...) kernel<<<(grid), (block), 0, (stream)>>>(__VA_ARGS__)
#define NS_LAUNCH_CHECK() C10_CUDA_KERNEL_LAUNCH_CHECK()
#endif

namespace nsplat {

constexpr int kThreads = 256;  // block size of the light kernels

// Blocks for a grid-stride loop over n elements (n > 0).
inline unsigned int blocks_for(int64_t n, int threads) {
  const int64_t b = (n + threads - 1) / threads;
  return static_cast<unsigned int>(std::min<int64_t>(std::max<int64_t>(b, 1), 1 << 20));
}

#if defined(NSPLAT_CUDA_EMULATE)
using Stream = emu::Stream;
using DeviceGuard = emu::DeviceGuard;
inline Stream current_stream() { return emu::current_stream(); }
#else
using Stream = cudaStream_t;
using DeviceGuard = c10::cuda::CUDAGuard;
inline Stream current_stream() { return c10::cuda::getCurrentCUDAStream(); }
#endif

// Reads of device values by the host (each one a synchronisation on a GPU), counted for the tests (the module's
// host_reads()); every such read of the backend goes through to_host.
inline std::atomic<int64_t>& host_read_count() {
  static std::atomic<int64_t> count{0};
  return count;
}

inline at::Tensor to_host(const at::Tensor& t) {
  ++host_read_count();
  return t.to(at::kCPU);
}

// Raw device buffer of n bytes (at least 1) from PyTorch's caching allocator.
inline at::Tensor bytes(int64_t n, const at::TensorOptions& dev) {
  return at::empty({std::max<int64_t>(n, 1)}, dev.dtype(at::kByte));
}

template <typename T>
inline T* as(at::Tensor& t) { return reinterpret_cast<T*>(t.data_ptr()); }

// Ascending sort of n 64-bit keys below 2^bits (cub radix sort over their low `bits` bits).
inline void sort_keys(const uint64_t* in, uint64_t* out, int64_t n, int bits, const at::TensorOptions& dev,
                      Stream stream) {
#if defined(NSPLAT_CUDA_EMULATE)
  (void)dev; (void)stream; (void)bits;
  ++emu::launch_count;
  std::copy(in, in + n, out);
  std::sort(out, out + n);
#else
  size_t temp_bytes = 0;
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortKeys(nullptr, temp_bytes, in, out, static_cast<int>(n), 0, bits, stream));
  at::Tensor temp = bytes(static_cast<int64_t>(temp_bytes), dev);
  C10_CUDA_CHECK(
      cub::DeviceRadixSort::SortKeys(temp.data_ptr(), temp_bytes, in, out, static_cast<int>(n), 0, bits, stream));
#endif
}

// Stable ascending sort of n (key, value) pairs by the keys' low `bits` bits (cub radix sort).
inline void sort_pairs(const uint64_t* keys_in, uint64_t* keys_out, const int* vals_in, int* vals_out, int64_t n, int bits,
                       const at::TensorOptions& dev, Stream stream) {
#if defined(NSPLAT_CUDA_EMULATE)
  (void)dev; (void)stream; (void)bits;
  ++emu::launch_count;
  std::vector<int64_t> order(static_cast<size_t>(n));
  for (int64_t i = 0; i < n; ++i) order[static_cast<size_t>(i)] = i;
  std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return keys_in[a] < keys_in[b]; });
  for (int64_t i = 0; i < n; ++i) {
    keys_out[i] = keys_in[order[static_cast<size_t>(i)]];
    vals_out[i] = vals_in[order[static_cast<size_t>(i)]];
  }
#else
  size_t temp_bytes = 0;
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, keys_in, keys_out, vals_in, vals_out,
                                                 static_cast<int>(n), 0, bits, stream));
  at::Tensor temp = bytes(static_cast<int64_t>(temp_bytes), dev);
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp.data_ptr(), temp_bytes, keys_in, keys_out, vals_in, vals_out,
                                                 static_cast<int>(n), 0, bits, stream));
#endif
}

// out[i] = sum of in[0..i) over n entries.
inline void exclusive_sum(const int64_t* in, int64_t* out, int64_t n, const at::TensorOptions& dev, Stream stream) {
#if defined(NSPLAT_CUDA_EMULATE)
  (void)dev; (void)stream;
  ++emu::launch_count;
  int64_t acc = 0;
  for (int64_t i = 0; i < n; ++i) { out[i] = acc; acc += in[i]; }
#else
  size_t temp_bytes = 0;
  C10_CUDA_CHECK(cub::DeviceScan::ExclusiveSum(nullptr, temp_bytes, in, out, static_cast<int>(n), stream));
  at::Tensor temp = bytes(static_cast<int64_t>(temp_bytes), dev);
  C10_CUDA_CHECK(cub::DeviceScan::ExclusiveSum(temp.data_ptr(), temp_bytes, in, out, static_cast<int>(n), stream));
#endif
}

#define NS_GRID_STRIDE(i, n) \
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < (n); \
       i += static_cast<int64_t>(blockDim.x) * gridDim.x)

}  // namespace nsplat
