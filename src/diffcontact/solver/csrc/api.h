// The boundary between the compiled kernel and Python: the one definition of the status codes, the failure rule,
// the weak-cone threshold and the arguments of the entry points.  lanes_module.cpp fills these structs from the
// arguments of the module's functions (kernel.py calls them); kernel.py checks, when it loads the module, that its
// copies of the status codes, the failure rule and the threshold agree with _lanes.constants().
//
// Plain C declarations, no headers: included by the per-ISA translation units (which switch the target first)
// as well as by lanes_module.cpp.
#ifndef DIFFCONTACT_API_H
#define DIFFCONTACT_API_H

typedef long long i64;

// Per-element status (diffcontact.solver.Status).  The first four are reported by the interior-point method; the
// last by the least-norm stage of singular problems (least_norm.py) as well.
enum {
  CONVERGED = 0,   // residual after polishing at most final_tol
  INACCURATE = 1,  // not converged, residual at most acceptable_tol (usable)
  MAX_ITER = 2,    // not converged, residual above acceptable_tol
  NUMERICAL = 3,   // non-finite values or a failed factorisation
  UNBOUNDED = 4,   // the objective is unbounded below on the cones
};
// The failure rule: an element whose status is at least this one has no usable solution (returned as zeros).
enum { FIRST_FAILURE = MAX_ITER };
// A ray or cone whose multiplier is at most WEAK_TOL·max(1, ‖slack‖) is weakly active (a contact exactly at a
// stick/slip or touch/separate switch): polishing and the backward pass may take it as inactive.
#define WEAK_TOL 1e-6
// Version of this interface: raise it with any change of the structs or the entry points.
enum { API_VERSION = 6 };

// _lanes.solve: the interior-point method to ipm_tol, then (polish_steps > 0) polishing, of the batch
// elements idx[start..stop) of B problems in the standard form of kernel.py (K contacts of dimension d, n = K·d;
// arrays C-contiguous, row-major).  Writes the rows idx[start..stop) of the outputs.  P = T·A·T is formed per group
// as it is gathered (P_ij = T_i·A_ij·T_j, plus 1 on the diagonal where T_i = 0: a row the answer does not depend on;
// T in `scale`).
struct SolveArgs {
  const double* A;           // (B, n, n) symmetric
  const double* scale;       // (B, n) T
  const double* c;           // (B, n)
  const double* lower;       // (B, K)
  const unsigned char* on;   // (B, K) cones in use
  const unsigned char* on_l; // (B, K) rays in use
  i64 K, d;
  const i64* idx;            // the elements to solve
  double ipm_tol;            // target of the interior-point method (before polishing)
  double final_tol;          // residual at most this after polishing: CONVERGED
  double acceptable_tol;     // else at most this: INACCURATE, else MAX_ITER
  i64 max_iter;
  double start_margin;       // how far inside the cones the starting point lies
  double refine_tol;         // a gap below refine_tol·max(1, ‖z‖∞): refine the Newton directions once
  i64 polish_steps;          // at most this many factorisations per polishing pass (0: no polishing)
  double* z;                 // (B, n) outputs: solution,
  double* s_l;               // (B, K) slacks and multipliers of the rays,
  double* lam_l;             // (B, K)
  double* s_q;               // (B, K, d) of the cones,
  double* lam_q;             // (B, K, d)
  i64* status;               // (B,) status codes above,
  i64* iterations;           // (B,) interior-point iterations,
  double* residual;          // (B,) scaled KKT residual of the returned point
  double* trace;             // (B, T, 4) per iteration: primal, dual residual, gap, step (T may be 0)
  i64 T;
};

// _lanes.adjoint: Kᵀ[u; v] = [g; 0] (implicit.py) of the elements start … stop − 1, the weakly active
// cones of singular elements taken as inactive.
struct AdjointArgs {
  const double* A;           // (B, n, n): P = T·A·T as SolveArgs
  const double* scale;       // (B, n) T
  const double* s_l;         // (B, K) the solution: as SolveArgs
  const double* lam_l;       // (B, K)
  const double* s_q;         // (B, K, d)
  const double* lam_q;       // (B, K, d)
  const unsigned char* on;   // (B, K)
  const unsigned char* on_l; // (B, K)
  i64 K, d;
  const double* g;           // (B, n) right-hand side
  double* u;                 // (B, n) outputs: u,
  double* v_l;               // (B, K) the rays' v,
  unsigned char* ok;         // (B,) 0 where K is singular even with the weakly active cones taken as inactive
};

// _lanes.flat: for the elements start … stop − 1, whether ½(A + Aᵀ) on the rows in use (active contacts,
// without the tangential rows of μ = 0 contacts) minus tol·ref·I is not positive definite (its Cholesky factorisation
// fails), ref its largest diagonal entry on those rows; an element with ref ≤ 0 is flat, one without rows in use not
// (least_norm.py, flat_elements).  Also, in the same pass over A, whether all of its entries are finite (the input check)
// and whether it equals its transpose exactly (then the scaling uses it without forming ½(A + Aᵀ)).
struct FlatArgs {
  const double* A;               // (B, n, n)
  const double* mu;              // (B, K)
  const unsigned char* active;   // (B, K)
  i64 K, d;
  double tol;
  unsigned char* flat;           // (B,) outputs: 1 where flat,
  unsigned char* finite;         // (B,) 1 where every entry of A is finite,
  unsigned char* symmetric;      // (B,) 1 where A equals its transpose
};

#endif
