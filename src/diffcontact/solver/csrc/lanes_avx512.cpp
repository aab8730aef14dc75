// The kernel for AVX-512 (8 lanes of float64).
#if defined(__x86_64__)
#pragma GCC target("avx512f,avx512dq,avx512vl,avx2,fma")
#define LANES 8
#define NS isa_avx512
#include "lanes_entry.hpp"
#endif
