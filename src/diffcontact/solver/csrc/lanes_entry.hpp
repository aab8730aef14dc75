// The entry points of one instruction set (namespace NS): the interior-point method with polishing, and the
// adjoint solve, over batch elements taken W at a time (the last group padded with copies of its last element).
#include "ipm_lanes.hpp"
#include "exact_lanes.hpp"

namespace NS {

int lanes() { return LANES; }

template <int D>
static void gather_problem(Work<D>& w, const i64* b, const double* P, const double* c, const double* low,
                           const unsigned char* on, const unsigned char* onl) {
  const int K = w.K;
  const i64 n = w.n;
  for (i64 i = 0; i < n * n; i++)
    for (int l = 0; l < LANES; l++) w.P[i][l] = P[b[l] * n * n + i];
  for (i64 i = 0; i < n; i++)
    for (int l = 0; l < LANES; l++) w.c[i][l] = c ? c[b[l] * n + i] : 0.0;
  for (int k = 0; k < K; k++)
    for (int l = 0; l < LANES; l++) {
      w.onl[k][l] = onl[b[l] * K + k] ? -1 : 0;
      w.on[k][l] = (D > 1 && on[b[l] * K + k]) ? -1 : 0;
      w.h_l[k][l] = (low && onl[b[l] * K + k]) ? -low[b[l] * K + k] : 0.0;
    }
}

template <int D>
static void* alloc_work(Work<D>& w, Exact<D>& e, int K) {
  void* mem = nullptr;
  i64 size = Work<D>::size(K) + Exact<D>::size(K);
  if (posix_memalign(&mem, 64, sizeof(V) * size) != 0) return nullptr;
  w.carve((V*)mem, K);
  e.carve((V*)mem + Work<D>::size(K), K);
  return mem;
}

template <int D>
static int solve_indices(const double* P, const double* c, const double* low, const unsigned char* on,
                         const unsigned char* onl, int K, const i64* idx, i64 m, const Options& o, double* z,
                         double* s_l, double* lam_l, double* s_q, double* lam_q, i64* status, i64* iters,
                         double* res, unsigned char* again, double* trace, i64 T) {
  const i64 n = (i64)K * D;
  Work<D> w;
  Exact<D> e;
  void* mem = alloc_work(w, e, K);
  if (!mem) return -1;
  for (i64 g = 0; g < m; g += LANES) {
    i64 b[LANES];
    for (int l = 0; l < LANES; l++) b[l] = idx[g + l < m ? g + l : m - 1];
    gather_problem(w, b, P, c, low, on, onl);
    double* tr[LANES];
    for (int l = 0; l < LANES; l++) tr[l] = (T > 0 && g + l < m) ? trace + b[l] * T * 4 : nullptr;
    i64 st[LANES], it[LANES];
    double r[LANES];
    solve_group<D>(w, o, st, it, r, tr, T);
    if (o.polish_steps > 0) {
      M run;
      for (int l = 0; l < LANES; l++) run[l] = st[l] <= MAX_ITER ? -1 : 0;
      if (any(run)) {
        V rp = polish(e, w, o.polish_steps, run);
        for (int l = 0; l < LANES; l++)
          if (run[l]) r[l] = rp[l];
      }
    }
    const double thr = o.last ? o.final_tol : (o.final_tol < 1e-13 ? o.final_tol : 1e-13);
    for (int l = 0; l < LANES && g + l < m; l++) {
      const i64 el = b[l];
      unsigned char more = 0;
      if (st[l] <= MAX_ITER) {  // (numerical trouble or unbounded: reported as such)
        if (r[l] <= thr) {
          st[l] = CONVERGED;
        } else {
          st[l] = r[l] <= o.acc_tol ? INACCURATE : MAX_ITER;
          more = !o.last;
        }
      }
      for (i64 i = 0; i < n; i++) {
        z[el * n + i] = w.zb[i][l];
        s_q[el * n + i] = w.sqb[i][l];
        lam_q[el * n + i] = w.lqb[i][l];
      }
      for (int k = 0; k < K; k++) {
        s_l[el * K + k] = w.slb[k][l];
        lam_l[el * K + k] = w.llb[k][l];
      }
      status[el] = st[l];
      iters[el] = it[l];
      res[el] = r[l];
      again[el] = more;
    }
  }
  free(mem);
  return 0;
}

template <int D>
static int adjoint_range(const double* P, const double* s_l, const double* lam_l, const double* s_q,
                         const double* lam_q, const unsigned char* on, const unsigned char* onl, int K,
                         const double* g, i64 b0, i64 b1, double* u, double* v_l, unsigned char* ok) {
  const i64 n = (i64)K * D;
  Work<D> w;
  Exact<D> e;
  void* mem = alloc_work(w, e, K);
  if (!mem) return -1;
  for (i64 g0 = b0; g0 < b1; g0 += LANES) {
    i64 b[LANES];
    for (int l = 0; l < LANES; l++) b[l] = g0 + l < b1 ? g0 + l : b1 - 1;
    gather_problem(w, b, P, nullptr, nullptr, on, onl);
    for (i64 i = 0; i < n; i++)
      for (int l = 0; l < LANES; l++) {
        w.sqb[i][l] = s_q[b[l] * n + i];
        w.lqb[i][l] = lam_q[b[l] * n + i];
        w.rhs[i][l] = g[b[l] * n + i];
      }
    for (int k = 0; k < K; k++)
      for (int l = 0; l < LANES; l++) {
        w.slb[k][l] = s_l[b[l] * K + k];
        w.llb[k][l] = lam_l[b[l] * K + k];
      }
    M good = adjoint(e, w, w.rhs);
    for (int l = 0; l < LANES && g0 + l < b1; l++) {
      const i64 el = b[l];
      for (i64 i = 0; i < n; i++) u[el * n + i] = e.dx[i][l];
      for (int k = 0; k < K; k++) v_l[el * K + k] = e.dx[n + k][l];
      ok[el] = good[l] ? 1 : 0;
    }
  }
  free(mem);
  return 0;
}

int solve(const double* P, const double* c, const double* low, const unsigned char* on, const unsigned char* onl,
          i64 K, i64 d, const i64* idx, i64 m, double tol_ipm, double tol, double acc_tol, i64 max_iter,
          double margin, double refine_tol, i64 polish_steps, i64 last, double* z, double* s_l, double* lam_l,
          double* s_q, double* lam_q, i64* status, i64* iters, double* res, unsigned char* again, double* trace,
          i64 T) {
  const Options o{tol_ipm, acc_tol, margin, refine_tol, max_iter, tol, (int)polish_steps, last != 0};
  const int k = (int)K;
#define SOLVE(DIM) \
  solve_indices<DIM>(P, c, low, on, onl, k, idx, m, o, z, s_l, lam_l, s_q, lam_q, status, iters, res, again, trace, T)
  switch (d) {
    case 1: return SOLVE(1);
    case 2: return SOLVE(2);
    case 3: return SOLVE(3);
    default: return -2;
  }
#undef SOLVE
}

int adjoint(const double* P, const double* s_l, const double* lam_l, const double* s_q, const double* lam_q,
            const unsigned char* on, const unsigned char* onl, i64 K, i64 d, const double* g, i64 b0, i64 b1,
            double* u, double* v_l, unsigned char* ok) {
  const int k = (int)K;
  switch (d) {
    case 1: return adjoint_range<1>(P, s_l, lam_l, s_q, lam_q, on, onl, k, g, b0, b1, u, v_l, ok);
    case 2: return adjoint_range<2>(P, s_l, lam_l, s_q, lam_q, on, onl, k, g, b0, b1, u, v_l, ok);
    case 3: return adjoint_range<3>(P, s_l, lam_l, s_q, lam_q, on, onl, k, g, b0, b1, u, v_l, ok);
    default: return -2;
  }
}

}  // namespace NS
