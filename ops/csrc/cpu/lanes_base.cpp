// The CPU sampler's tile search (lanes.h) compiled for the build's baseline instruction set (x86-64: SSE2); picked at run time by lanes_dispatch.cpp.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "lanes_api.h"
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#define NS_LANE_SEARCH lane_search_base
#if defined(__SSE2__)
#define NS_LANE_ISA 1
#else
#define NS_LANE_ISA 0
#endif
#include "lanes.h"
