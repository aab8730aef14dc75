// The entry points of one instruction set (namespace NS): the interior-point method with polishing, the adjoint
// solve and the test for flat directions, over batch elements taken W at a time (the last group padded with copies
// of its last element).
#include "api.h"
#include "ipm_lanes.hpp"
#include "exact_lanes.hpp"

namespace NS {

// P = T·A·T of the group's elements (api.h), c, the cones and rays in use and the rays' bounds (as −low in h_l).
template <int D>
static void gather_problem(Work<D>& w, const i64* b, const double* A, const double* T, const double* c,
                           const double* low, const unsigned char* on, const unsigned char* onl) {
  const int K = w.K;
  const i64 n = w.n;
  const double *Al[LANES], *Tl[LANES];
  for (int l = 0; l < LANES; l++) Al[l] = A + b[l] * n * n, Tl[l] = T + b[l] * n;
  for (i64 i = 0; i < n; i++) {
    V ti;
    for (int l = 0; l < LANES; l++) ti[l] = Tl[l][i];
    V* Pi = w.P + i * n;
    for (i64 j = 0; j < n; j++) {
      V a, tj;
      for (int l = 0; l < LANES; l++) a[l] = Al[l][i * n + j], tj[l] = Tl[l][j];
      Pi[j] = ti * a * tj;
    }
    Pi[i] = sel(ti == 0.0, Pi[i] + 1.0, Pi[i]);
  }
  for (i64 i = 0; i < n; i++)
    for (int l = 0; l < LANES; l++) w.c[i][l] = c ? c[b[l] * n + i] : 0.0;
  for (int k = 0; k < K; k++)
    for (int l = 0; l < LANES; l++) {
      w.onl[k][l] = onl[b[l] * K + k] ? -1 : 0;
      w.on[k][l] = (D > 1 && on[b[l] * K + k]) ? -1 : 0;
      w.h_l[k][l] = (low && onl[b[l] * K + k]) ? -low[b[l] * K + k] : 0.0;
    }
}

// Calls body(w, e, b, valid) for the lane groups of the elements start … stop − 1 with one thread's work arrays:
// b holds the group's batch indices (idx[j], or j if idx is null; the last group padded with copies of its last
// element), of which the first `valid` are its own.  Returns 0, or −1 if out of memory.
template <int D, class Body>
static int for_groups(int K, const i64* idx, i64 start, i64 stop, Body body) {
  Work<D> w;
  Exact<D> e;
  void* mem = nullptr;
  if (posix_memalign(&mem, 64, sizeof(V) * (Work<D>::size(K) + Exact<D>::size(K))) != 0) return -1;
  w.carve((V*)mem, K);
  e.carve((V*)mem + Work<D>::size(K), K);
  for (i64 g = start; g < stop; g += LANES) {
    i64 b[LANES];
    for (int l = 0; l < LANES; l++) {
      const i64 j = g + l < stop ? g + l : stop - 1;
      b[l] = idx ? idx[j] : j;
    }
    body(w, e, b, stop - g < LANES ? (int)(stop - g) : LANES);
  }
  free(mem);
  return 0;
}

template <int D>
static int solve_indices(const SolveArgs& a, i64 start, i64 stop) {
  const int K = (int)a.K;
  const i64 n = (i64)K * D, T = a.T;
  return for_groups<D>(K, a.idx, start, stop, [&](Work<D>& w, Exact<D>& e, const i64* b, int valid) {
    gather_problem(w, b, a.A, a.scale, a.c, a.lower, a.on, a.on_l);
    double* tr[LANES];
    for (int l = 0; l < LANES; l++) tr[l] = (T > 0 && l < valid) ? a.trace + b[l] * T * 4 : nullptr;
    i64 st[LANES], it[LANES];
    double r[LANES];
    solve_group<D>(w, a, st, it, r, tr);
    if (a.polish_steps > 0) {
      M run;
      for (int l = 0; l < LANES; l++) run[l] = st[l] <= MAX_ITER ? -1 : 0;
      if (any(run)) {
        V rp = polish(e, w, (int)a.polish_steps, run);
        for (int l = 0; l < LANES; l++)
          if (run[l]) r[l] = rp[l];
      }
    }
    for (int l = 0; l < valid; l++) {
      const i64 el = b[l];
      if (st[l] <= MAX_ITER)  // (numerical trouble or unbounded: reported as such)
        st[l] = r[l] <= a.final_tol ? CONVERGED : r[l] <= a.acceptable_tol ? INACCURATE : MAX_ITER;
      for (i64 i = 0; i < n; i++) {
        a.z[el * n + i] = w.zb[i][l];
        a.s_q[el * n + i] = w.sqb[i][l];
        a.lam_q[el * n + i] = w.lqb[i][l];
      }
      for (int k = 0; k < K; k++) {
        a.s_l[el * K + k] = w.slb[k][l];
        a.lam_l[el * K + k] = w.llb[k][l];
      }
      a.status[el] = st[l];
      a.iterations[el] = it[l];
      a.residual[el] = r[l];
    }
  });
}

template <int D>
static int adjoint_range(const AdjointArgs& a, i64 start, i64 stop) {
  const int K = (int)a.K;
  const i64 n = (i64)K * D;
  return for_groups<D>(K, nullptr, start, stop, [&](Work<D>& w, Exact<D>& e, const i64* b, int valid) {
    gather_problem(w, b, a.A, a.scale, nullptr, nullptr, a.on, a.on_l);
    for (i64 i = 0; i < n; i++)
      for (int l = 0; l < LANES; l++) {
        w.sqb[i][l] = a.s_q[b[l] * n + i];
        w.lqb[i][l] = a.lam_q[b[l] * n + i];
        w.rhs[i][l] = a.g[b[l] * n + i];
      }
    for (int k = 0; k < K; k++)
      for (int l = 0; l < LANES; l++) {
        w.slb[k][l] = a.s_l[b[l] * K + k];
        w.llb[k][l] = a.lam_l[b[l] * K + k];
      }
    M good = adjoint(e, w, w.rhs);
    for (int l = 0; l < valid; l++) {
      const i64 el = b[l];
      for (i64 i = 0; i < n; i++) a.u[el * n + i] = e.dx[i][l];
      for (int k = 0; k < K; k++) a.v_l[el * K + k] = e.dx[n + k][l];
      a.ok[el] = good[l] ? 1 : 0;
    }
  });
}

// A plain dense matrix (row-major, n × n, lower triangle) for cholesky.
struct Dense {
  const V* H;
  int n;
  V operator()(int i, int j) const { return H[(i64)i * n + j]; }
};

template <int D>
static int flat_range(const FlatArgs& a, i64 start, i64 stop) {
  const int K = (int)a.K;
  const int n = K * D;
  return for_groups<D>(K, nullptr, start, stop, [&](Work<D>& w, Exact<D>&, const i64* b, int valid) {
    for (int k = 0; k < K; k++)  // contacts active (onl) and with friction (on)
      for (int l = 0; l < LANES; l++) {
        w.onl[k][l] = a.active[b[l] * K + k] ? -1 : 0;
        w.on[k][l] = a.mu[b[l] * K + k] != 0.0 ? -1 : 0;
      }
    for (i64 i = 0; i < (i64)n * n; i++)
      for (int l = 0; l < LANES; l++) w.P[i][l] = a.A[b[l] * n * n + i];
    V nf[4] = {};  // (x·0 is 0 for finite x, NaN for ±inf and NaN; four independent sums)
    for (i64 i = 0; i < (i64)n * n; i++) nf[i % 4] += w.P[i] * 0.0;
    const V nonfinite = (nf[0] + nf[1]) + (nf[2] + nf[3]);
    M sym = M{} == 0;
    for (int i = 0; i < n; i++)
      for (int j = 0; j < i; j++) sym &= w.P[(i64)i * n + j] == w.P[(i64)j * n + i];
    M* used = (M*)w.rhs;  // (n vectors of scratch)
    for (int i = 0; i < n; i++) used[i] = i % D == 0 ? w.onl[i / D] : w.onl[i / D] & w.on[i / D];
    V ref = splat(0.0);
    M any_used = M{} != 0;
    for (int i = 0; i < n; i++) {
      ref = sel(used[i], vmax(ref, w.P[(i64)i * n + i]), ref);
      any_used |= used[i];
    }
    const V shift = a.tol * ref;
    for (int i = 0; i < n; i++) {  // ½(A + Aᵀ) − shift·I on the rows in use, the identity elsewhere (lower triangle)
      V* Pi = w.P + (i64)i * n;
      for (int j = 0; j < i; j++) Pi[j] = sel(used[i] & used[j], 0.5 * (Pi[j] + w.P[(i64)j * n + i]), 0.0);
      Pi[i] = sel(used[i], Pi[i] - shift, 1.0);
    }
    M ok = cholesky(n, Dense{w.P, n}, w.L);
    M flat = any_used & (~ok | (ref <= 0.0));
    for (int l = 0; l < valid; l++) {
      a.flat[b[l]] = flat[l] ? 1 : 0;
      a.finite[b[l]] = nonfinite[l] == 0.0 ? 1 : 0;
      a.symmetric[b[l]] = sym[l] ? 1 : 0;
    }
  });
}

// f(Dim<d>{}) for the contact dimension d (1, 2 or 3: the compiled ones); −2 for any other.
template <int D>
struct Dim {
  static constexpr int value = D;
};
template <class F>
static int by_dim(i64 d, F f) {
  switch (d) {
    case 1: return f(Dim<1>{});
    case 2: return f(Dim<2>{});
    case 3: return f(Dim<3>{});
    default: return -2;
  }
}

int solve(const SolveArgs& a, i64 start, i64 stop) {
  return by_dim(a.d, [&](auto dim) { return solve_indices<decltype(dim)::value>(a, start, stop); });
}

int adjoint(const AdjointArgs& a, i64 start, i64 stop) {
  return by_dim(a.d, [&](auto dim) { return adjoint_range<decltype(dim)::value>(a, start, stop); });
}

int flat(const FlatArgs& a, i64 start, i64 stop) {
  return by_dim(a.d, [&](auto dim) { return flat_range<decltype(dim)::value>(a, start, stop); });
}

}  // namespace NS
