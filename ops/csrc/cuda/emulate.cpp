// Host emulation build of the CUDA backend (see emulate.h): splat_cuda.cu and projection_cuda.cu compiled by the
// host compiler, so that tests on machines without a GPU run their launch code and compare it with the CPU backend
// bit for bit. Not part of the CUDA module that ops/build.py builds (ops/build.py: CUDA_SOURCES).
#ifndef NSPLAT_CUDA_EMULATE
#define NSPLAT_CUDA_EMULATE 1
#endif
#include "splat_cuda.cu"
#include "projection_cuda.cu"
