// The entry point of one instruction set: NS::solve (see ipm_lanes.hpp), dispatching on the contact dimension.
#include "ipm_lanes.hpp"

namespace NS {
int lanes() { return LANES; }

int solve(const double* P, const double* c, const double* low, const unsigned char* on, const unsigned char* onl,
          i64 K, i64 d, const i64* idx, i64 m, double tol, double acc_tol, i64 max_iter, double margin,
          double refine_tol, double* z, double* s_l, double* lam_l, double* s_q, double* lam_q, i64* status,
          i64* iters, double* res, double* trace, i64 T) {
  const Options o{tol, acc_tol, margin, refine_tol, max_iter};
  const int k = (int)K;
  switch (d) {
    case 1: return solve_indices<1>(P, c, low, on, onl, k, idx, m, o, z, s_l, lam_l, s_q, lam_q, status, iters, res, trace, T);
    case 2: return solve_indices<2>(P, c, low, on, onl, k, idx, m, o, z, s_l, lam_l, s_q, lam_q, status, iters, res, trace, T);
    case 3: return solve_indices<3>(P, c, low, on, onl, k, idx, m, o, z, s_l, lam_l, s_q, lam_q, status, iters, res, trace, T);
    default: return -2;
  }
}
}  // namespace NS
