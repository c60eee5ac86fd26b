// Host emulation build of the CUDA backend (see emulate.h): splat_cuda.cu compiled by the host compiler, so
// that tests on machines without a GPU run its launch code and compare it with the CPU backend bit for bit.
// Not part of the CUDA module that ops/build.py builds (bindings.cpp + splat_cuda.cu).
#ifndef NSPLAT_CUDA_EMULATE
#define NSPLAT_CUDA_EMULATE 1
#endif
#include "splat_cuda.cu"
