// The kernel for AVX2 with FMA (4 lanes of float64).
#if defined(__x86_64__)
#pragma GCC target("avx2,fma")
#define LANES 4
#define NS isa_avx2
#include "lanes_entry.hpp"
#endif
