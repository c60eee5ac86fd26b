// The CPU sampler's tile search (lanes.h) compiled for avx512; picked at run time by lanes_dispatch.cpp.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "lanes_api.h"
#if defined(__x86_64__)
#include <immintrin.h>

#pragma GCC push_options
#pragma GCC target("avx2,fma,avx512f,avx512dq,avx512vl,avx512bw")
#define NS_LANE_SEARCH lane_search_avx512
#define NS_LANE_ISA 3
#include "lanes.h"
#pragma GCC pop_options
#endif
