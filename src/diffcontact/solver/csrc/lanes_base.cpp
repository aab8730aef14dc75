// The kernel for any CPU (2 lanes of float64: SSE2 on x86-64, NEON on arm64, scalar pairs elsewhere).
#define LANES 2
#define NS isa_base
#include "lanes_entry.hpp"
