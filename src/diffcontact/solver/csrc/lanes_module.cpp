// The lane-parallel interior-point kernel as a plain shared library, called through ctypes (see lanes.py; the
// interface is api.h).  The instruction set is chosen at run time, so one build runs on any x86-64 CPU (or on any
// other, with 2 lanes).
#include "api.h"

#define DECLARE(NS)                                         \
  namespace NS {                                            \
  int lanes();                                              \
  int solve(const SolveArgs& a, i64 start, i64 stop);       \
  int adjoint(const AdjointArgs& a, i64 start, i64 stop);   \
  int flat(const FlatArgs& a, i64 start, i64 stop);         \
  }
DECLARE(isa_base)
#if defined(__x86_64__)
DECLARE(isa_avx2)
DECLARE(isa_avx512)
#endif

static int (*solve_fn)(const SolveArgs&, i64, i64) = isa_base::solve;
static int (*adjoint_fn)(const AdjointArgs&, i64, i64) = isa_base::adjoint;
static int (*flat_fn)(const FlatArgs&, i64, i64) = isa_base::flat;
static int width = 2;

static const Constants constants = {
    API_VERSION, sizeof(SolveArgs), sizeof(AdjointArgs), sizeof(FlatArgs),          CONVERGED, INACCURATE, MAX_ITER, NUMERICAL,
    UNBOUNDED,   FIRST_FAILURE,     WEAK_TOL,
};

extern "C" {
// The facts of api.h, for lanes.py to check its copies against.
const Constants* diffcontact_constants() { return &constants; }

// Lane widths this CPU can run, best first: a bit set of 8, 4, 2.
int diffcontact_ipm_supported() {
  int s = 2;
#if defined(__x86_64__)
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) s |= 4;
  if ((s & 4) && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
      __builtin_cpu_supports("avx512vl"))
    s |= 8;
#endif
  return s;
}

// Select the kernel of lane width w (8, 4 or 2); returns the width selected, 0 if this CPU cannot run it.
int diffcontact_ipm_select(int w) {
  if (!(diffcontact_ipm_supported() & w)) return 0;
#if defined(__x86_64__)
  if (w == 8) solve_fn = isa_avx512::solve, adjoint_fn = isa_avx512::adjoint, flat_fn = isa_avx512::flat;
  if (w == 4) solve_fn = isa_avx2::solve, adjoint_fn = isa_avx2::adjoint, flat_fn = isa_avx2::flat;
#endif
  if (w == 2) solve_fn = isa_base::solve, adjoint_fn = isa_base::adjoint, flat_fn = isa_base::flat;
  width = w;
  return w;
}

int diffcontact_ipm_width() { return width; }

// The entry points of api.h over the elements start … stop − 1 (of idx for the solve).  Return 0, or −1 if out of
// memory, −2 for a contact dimension other than 1, 2, 3.
int diffcontact_ipm_solve(const SolveArgs* a, i64 start, i64 stop) { return solve_fn(*a, start, stop); }
int diffcontact_adjoint_solve(const AdjointArgs* a, i64 start, i64 stop) { return adjoint_fn(*a, start, stop); }
int diffcontact_flat_test(const FlatArgs* a, i64 start, i64 stop) { return flat_fn(*a, start, stop); }
}
