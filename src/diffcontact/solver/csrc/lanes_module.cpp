// diffcontact.solver._lanes: the lane-parallel interior-point kernel, called through ctypes (see lanes.py).
// The instruction set is chosen at run time, so one build runs on any x86-64 CPU (or on any other, with 2 lanes).
#include <Python.h>

typedef long long i64;
#define SOLVE_ARGS                                                                                                  \
  const double *P, const double *c, const double *low, const unsigned char *on, const unsigned char *onl, i64 K,   \
      i64 d, const i64 *idx, i64 m, double tol_ipm, double tol, double acc_tol, i64 max_iter, double margin,       \
      double refine_tol, i64 polish_steps, i64 last, double *z, double *s_l, double *lam_l, double *s_q,           \
      double *lam_q, i64 *status, i64 *iters, double *res, unsigned char *again, double *trace, i64 T
#define SOLVE_CALL                                                                                                  \
  P, c, low, on, onl, K, d, idx, m, tol_ipm, tol, acc_tol, max_iter, margin, refine_tol, polish_steps, last, z, s_l, \
      lam_l, s_q, lam_q, status, iters, res, again, trace, T
#define ADJOINT_ARGS                                                                                              \
  const double *P, const double *s_l, const double *lam_l, const double *s_q, const double *lam_q,               \
      const unsigned char *on, const unsigned char *onl, i64 K, i64 d, const double *g, i64 b0, i64 b1, double *u, \
      double *v_l, unsigned char *ok
#define ADJOINT_CALL P, s_l, lam_l, s_q, lam_q, on, onl, K, d, g, b0, b1, u, v_l, ok
#define DECLARE(NS)          \
  namespace NS {             \
  int lanes();               \
  int solve(SOLVE_ARGS);     \
  int adjoint(ADJOINT_ARGS); \
  }
DECLARE(isa_base)
#if defined(__x86_64__)
DECLARE(isa_avx2)
DECLARE(isa_avx512)
#endif

static int (*solve_fn)(SOLVE_ARGS) = isa_base::solve;
static int (*adjoint_fn)(ADJOINT_ARGS) = isa_base::adjoint;
static int width = 2;

extern "C" {
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
  if (w == 8) solve_fn = isa_avx512::solve, adjoint_fn = isa_avx512::adjoint;
  if (w == 4) solve_fn = isa_avx2::solve, adjoint_fn = isa_avx2::adjoint;
#endif
  if (w == 2) solve_fn = isa_base::solve, adjoint_fn = isa_base::adjoint;
  width = w;
  return w;
}

int diffcontact_ipm_width() { return width; }

// The interior-point method (to tol_ipm) and, if polish_steps > 0, polishing of the batch elements idx[0..m) of
// the (B, …) arrays P (B,n,n), c (B,n), low, on, onl (B,K), into z (B,n), s_l, lam_l (B,K), s_q, lam_q (B,n),
// status, iters (B,) int64, res (B,), again (B,) uint8 (marked for a pass to the full tolerance: not converged to
// rounding level, unless `last`) and trace (B,T,4) (T may be 0).  Returns 0, or −1 if out of memory, −2 for a
// contact dimension other than 1, 2, 3.
int diffcontact_ipm_solve(SOLVE_ARGS) { return solve_fn(SOLVE_CALL); }

// The adjoint Kᵀ[u; v] = [g; 0] of the elements b0 … b1−1 (exact.py): u (B,n), the rays' v_l (B,K), ok (B,)
// uint8 (0 where K is singular even with weakly active cones taken as inactive).  Returns as above.
int diffcontact_adjoint_solve(ADJOINT_ARGS) { return adjoint_fn(ADJOINT_CALL); }
}

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_lanes", "Lane-parallel interior-point kernel (called through ctypes).", -1, nullptr,
    nullptr,               nullptr,  nullptr,                                                          nullptr};
PyMODINIT_FUNC PyInit__lanes(void) { return PyModule_Create(&module); }
