// The CPU sampler's tile search (lanes.h) compiled for avx2; picked at run time by lanes_dispatch.cpp.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "lanes_api.h"
#if defined(__x86_64__)
#include <immintrin.h>

#pragma GCC push_options
#pragma GCC target("avx2,fma")
#define NS_LANE_SEARCH lane_search_avx2
#define NS_LANE_ISA 2
#include "lanes.h"
#pragma GCC pop_options
#endif
