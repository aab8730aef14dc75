// diffcontact.solver._lanes: the lane-parallel interior-point kernel, called through ctypes (see lanes.py).
// The instruction set is chosen at run time, so one build runs on any x86-64 CPU (or on any other, with 2 lanes).
#include <Python.h>

typedef long long i64;
#define SOLVE_ARGS                                                                                                   \
  const double *P, const double *c, const double *low, const unsigned char *on, const unsigned char *onl, i64 K,    \
      i64 d, const i64 *idx, i64 m, double tol, double acc_tol, i64 max_iter, double margin, double refine_tol,     \
      double *z, double *s_l, double *lam_l, double *s_q, double *lam_q, i64 *status, i64 *iters, double *res,      \
      double *trace, i64 T
#define DECLARE(NS)        \
  namespace NS {           \
  int lanes();             \
  int solve(SOLVE_ARGS);   \
  }
DECLARE(isa_base)
#if defined(__x86_64__)
DECLARE(isa_avx2)
DECLARE(isa_avx512)
#endif

static int (*solve_fn)(SOLVE_ARGS) = isa_base::solve;
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
  if (w == 8) solve_fn = isa_avx512::solve;
  if (w == 4) solve_fn = isa_avx2::solve;
#endif
  if (w == 2) solve_fn = isa_base::solve;
  width = w;
  return w;
}

int diffcontact_ipm_width() { return width; }

// Solve the batch elements idx[0..m) of the (B, …) arrays P (B,n,n), c (B,n), low, on, onl (B,K) into z (B,n),
// s_l, lam_l (B,K), s_q, lam_q (B,n), status, iters (B,) int64, res (B,) and trace (B,T,4) (T may be 0).
// Returns 0, or −1 if out of memory, −2 for a contact dimension other than 1, 2, 3.
int diffcontact_ipm_solve(SOLVE_ARGS) {
  return solve_fn(P, c, low, on, onl, K, d, idx, m, tol, acc_tol, max_iter, margin, refine_tol, z, s_l, lam_l, s_q,
                  lam_q, status, iters, res, trace, T);
}
}

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_lanes", "Lane-parallel interior-point kernel (called through ctypes).", -1, nullptr,
    nullptr,               nullptr,  nullptr,                                                          nullptr};
PyMODINIT_FUNC PyInit__lanes(void) { return PyModule_Create(&module); }
