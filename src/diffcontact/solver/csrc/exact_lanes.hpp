// Newton's method on the exact optimality conditions, W problems at a time (see kkt.py for the equations):
// polishing of the interior-point solution and the adjoint solve of the backward pass.
//
// The linearised conditions K (unknowns dz, the rays' dλ_l, the cones' dλ_q) are reduced exactly to n + K unknowns
// (dz, dλ_l): a used cone's multiplier enters its contact's stationarity rows with coefficient −1, so those rows
// give dλ_q = Stat·x − b_stat, and its complementarity rows E dz_k + C dλ_q = b_cone become
// (E + C·Stat) x = b_cone + C b_stat, with C = L(s), E = L(λ) (arrow matrices), or C = I, E = 0 for a weakly
// active cone taken as inactive.  A contact without a cone keeps its stationarity rows (C = I, E = 0 as well, with
// its dλ_q = b_cone decoupled); a ray not in use is an identity row.
//
// The K rays' unknowns are eliminated before the LU: ray k's row has two entries, a = λ_l at dz_kD and b = s_l at
// dλ_l,k (0 and 1 for an identity row), and dλ_l,k appears elsewhere only in contact k's D rows (Bc: −C_k[i, 0]).
// Per lane the larger of |a|, |b| is the pivot: with b, dλ_l,k = (g − a dz_kD)/b is substituted (column kD of the
// n × n block A becomes A_kD − Bc·a/b); with a, dz_kD and dλ_l,k trade places (dz_kD = (g − b dλ_l,k)/a, column kD
// becomes Bc − A_kD·b/a).  Either is a change of one column: the Schur complement S (n × n, the same size in every
// lane) is factorised by LU with partial pivoting (pivots chosen per lane), and the eliminated unknowns follow from
// the ray rows; A's original columns kD are kept for the right-hand sides.  Included by lanes_entry.hpp after
// ipm_lanes.hpp (same namespace and types).

namespace NS {

// Halvings of a polishing Newton step that does not lower the residual, before polishing stops; only near a
// solution (residual at most DAMP_BELOW): from farther, the interior-point point is not near one by the exact
// measure (as where the scaling's size estimate is far off), and the retries take over.
constexpr int DAMPING = 4;
constexpr double DAMP_BELOW = 1e-3;
// The exact KKT residual (relative to max(1, ‖z‖∞)) at which polishing, and the faces step, count a point polished.
constexpr double POLISHED = 1e-14;

// The exact conditions of one group: reduced matrix and its LU factors, per-cone coefficients, residuals.
template <int D>
struct Exact {
  int K, n, N;       // N = n + K
  V *R, *R2;         // current factors and a new factorisation: Factors<D> layout (F vectors)
  M *piv, *piv2;     // n: pivot row of each step, per lane
  V *scale, *scale2; // 1: Frobenius norm (singularity test)
  V *x, *dx, *y;     // N + n: right-hand side, solution (stationarity, rays, cones), reduced work
  V *r_z, *r_l, *r_q, *comp_l, *comp_q;  // residuals at the current point
  V *t_z, *t_l, *t_q, *tc_l, *tc_q;      // residuals at the trial point
  V *zt, *slt, *llt, *sqt, *lqt;         // trial point
  V *h_l;

  static i64 F(int K) {  // S (n × n), A's columns kD (K × n), per ray: c, 1/d, swapped; C (see Factors)
    i64 n = (i64)K * D;
    return n * n + (i64)K * n + 3 * K + (i64)K * D * D;
  }
  static i64 size(int K) {
    i64 n = (i64)K * D, N = n + K;
    return 2 * F(K) + 2 * n + 2 + 3 * (N + n) + 3 * n + 2 * K + 3 * n + 2 * K + 3 * n +
           2 * K + K;
  }
  void carve(V* buf, int K_) {
    K = K_;
    n = K * D;
    N = n + K;
    V* p = buf;
    auto take = [&p](i64 m) {
      V* r = p;
      p += m;
      return r;
    };
    R = take(F(K)), R2 = take(F(K));
    piv = (M*)take(n), piv2 = (M*)take(n);
    for (int i = 0; i < n; i++) piv[i] = piv2[i] = M{} + i;  // (lanes never factorised still solve in bounds)
    scale = take(1), scale2 = take(1);
    x = take(N + n), dx = take(N + n), y = take(N + n);
    r_z = take(n), r_q = take(n), comp_q = take(n), r_l = take(K), comp_l = take(K);
    t_z = take(n), t_q = take(n), tc_q = take(n), t_l = take(K), tc_l = take(K);
    zt = take(n), sqt = take(n), lqt = take(n), slt = take(K), llt = take(K);
    h_l = take(K);
  }
};

// The parts of a factorisation record (Exact::R, R2): the LU factors of S (n × n, row-major), A's original column
// kD of each ray k (K × n), per ray the other entry c of its row, 1/d of its pivot d and whether dz_kD and
// dλ_l,k traded places, and the coefficients C (K × D × D) of dλ_q in the cone rows.
template <int D>
struct Factors {
  V *S, *colA, *c, *dinv, *C;
  M* swp;
  Factors(V* R, int K) {
    const i64 n = (i64)K * D;
    S = R, colA = R + n * n, c = colA + K * n, dinv = c + K, swp = (M*)(dinv + K), C = dinv + 2 * K;
  }
};

// A ray / cone whose multiplier is negligible next to its slack (api.h; in Python exact._weak_ray, exact._weak_cone).
static inline M weak_ray(V s, V lam) { return lam <= WEAK_TOL * vmax(splat(1.0), vabs(s)); }
template <int D>
static inline M weak_cone(const V* s, const V* lam) {
  V ns = splat(0.0), nl = splat(0.0);
  for (int i = 0; i < D; i++) ns += s[i] * s[i], nl += lam[i] * lam[i];
  return vsqrt(nl) <= WEAK_TOL * vmax(splat(1.0), vsqrt(ns));
}

// Exact KKT residuals (complementarity s∘λ = 0) at (z, s, λ) into r_*, comp_*; returns their max relative to
// max(1, ‖z‖∞), counting any violation of the cones as well.
template <int D>
static V kkt_residual(const Work<D>& w, const V* h_l, const V* z, const V* s_l, const V* lam_l, const V* s_q,
                      const V* lam_q, V* r_z, V* r_l, V* r_q, V* comp_l, V* comp_q) {
  const int K = w.K, n = w.n;
  const V zero = splat(0.0);
  V worst = zero;
  matvec<false>(n, w.P, z, [&](int i) { return w.c[i]; }, [&](int i, V t) { r_z[i] = t; });
  const V zmax = size_of(z, n);
  for (int k = 0; k < K; k++) {
    M ul = w.onl[k], uq = w.on[k];
    r_z[k * D] -= sel(ul, lam_l[k], zero);
    r_l[k] = sel(ul, -z[k * D] + s_l[k] - h_l[k], zero);
    comp_l[k] = sel(ul, s_l[k] * lam_l[k], zero);
    worst = sel(ul, vmax(worst, vmax(vmax(vabs(r_l[k]), vabs(comp_l[k])), vmax(-s_l[k], -lam_l[k]))), worst);
    if (D > 1) {
      V rs = zero, rl = zero, dot = zero;
      for (int i = 0; i < D; i++) {
        int r = k * D + i;
        r_z[r] -= sel(uq, lam_q[r], zero);
        r_q[r] = sel(uq, -z[r] + s_q[r], zero);
        dot += s_q[r] * lam_q[r];
        if (i > 0) rs += s_q[r] * s_q[r], rl += lam_q[r] * lam_q[r];
      }
      comp_q[k * D] = sel(uq, dot, zero);
      for (int i = 1; i < D; i++)
        comp_q[k * D + i] = sel(uq, s_q[k * D] * lam_q[k * D + i] + lam_q[k * D] * s_q[k * D + i], zero);
      V wq = vmax(vsqrt(rs) - s_q[k * D], vsqrt(rl) - lam_q[k * D]);
      for (int i = 0; i < D; i++) wq = vmax(wq, vmax(vabs(r_q[k * D + i]), vabs(comp_q[k * D + i])));
      worst = sel(uq, vmax(worst, wq), worst);
    } else {
      r_q[k] = zero, comp_q[k] = zero;
    }
  }
  for (int i = 0; i < n; i++) worst = vmax(worst, vabs(r_z[i]));
  return worst / zmax;
}

// rr[j] −= Σ_{c < m} rr[c0 + c]·prow[c][j] for j = j0 … N − 1 (a row's update by m pivot rows of a panel), the
// terms subtracted in the order of c as one column at a time; JB columns j at once (independent sums).
static inline void update_row(V* rr, const V* const* prow, int m, int c0, int j0, int N) {
  constexpr int JB = LANES >= 8 ? 8 : 4;
  const V* f = rr + c0;
  int j = j0;
  for (; j + JB <= N; j += JB) {
    V t[JB];
    for (int x = 0; x < JB; x++) t[x] = rr[j + x];
    for (int c = 0; c < m; c++) {
      V fc = f[c];
      const V* p = prow[c] + j;
      for (int x = 0; x < JB; x++) t[x] -= fc * p[x];
    }
    for (int x = 0; x < JB; x++) rr[j + x] = t[x];
  }
  for (; j < N; j++) {
    V t = rr[j];
    for (int c = 0; c < m; c++) t -= f[c] * prow[c][j];
    rr[j] = t;
  }
}

// The factorisation's first step: the reduced matrix at (s, λ) into f.S (row-major n × n), the cone rows'
// coefficients into f.C, and each ray's row (a at dz_kD, b at dλ_l,k) as its pivot: the larger of the two (|d|,
// 1/d in f.dinv, the other entry c in f.c, f.swp where a is the larger).  use_weak: lanes whose weakly active
// cones and rays are taken as inactive.  Adds the squares of the rays' entries to sq_rays and keeps the least
// |d| in dmin.
template <int D>
static void assemble(Factors<D>& f, const Work<D>& w, int K, int n, const V* s_l, const V* lam_l, const V* s_q,
                     const V* lam_q, M use_weak, V& sq_rays, V& dmin) {
  const V zero = splat(0.0), one = splat(1.0);
  V* R = f.S;
  for (int k = 0; k < K; k++) {
    M uq = w.on[k];
    M weak = uq & use_weak & weak_cone<D>(s_q + k * D, lam_q + k * D);
    M arrow = uq & ~weak;
    const V* s = s_q + k * D;
    const V* lam = lam_q + k * D;
    V Ck[D * D];
    for (int i = 0; i < D; i++)
      for (int j = 0; j < D; j++) {
        V l = (i == 0) ? s[j] : (j == 0 ? s[i] : (j == i ? s[0] : zero));  // L(s)[i, j]
        Ck[i * D + j] = sel(arrow, l, i == j ? one : zero);
        f.C[(k * D + i) * D + j] = Ck[i * D + j];
      }
    for (int i = 0; i < D; i++) {
      V* row = R + (i64)(k * D + i) * n;
      const V* Prow = w.P + (i64)(k * D) * n;
      for (int t = 0; t < n; t++) {  // C_k times P's rows of contact k (in one pass)
        V a = zero;
        for (int j = 0; j < D; j++) a += Ck[i * D + j] * Prow[(i64)j * n + t];
        row[t] = a;
      }
      for (int j = 0; j < D; j++) {
        V l = (i == 0) ? lam[j] : (j == 0 ? lam[i] : (j == i ? lam[0] : zero));  // L(λ)[i, j]
        row[k * D + j] += sel(arrow, l, zero);
      }
      V cb = sel(w.onl[k], -Ck[i * D], zero);  // Bc: the entry of dλ_l,k (Stat[kD, n + k] = −1 for a ray in use)
      sq_rays += cb * cb;
    }
    M ul = w.onl[k];
    M wr = ~ul | (use_weak & weak_ray(s_l[k], lam_l[k]));
    V a = sel(wr, zero, lam_l[k]), b = sel(wr, one, s_l[k]);  // the ray's row: a at dz_kD, b at dλ_l,k
    sq_rays += a * a + b * b;
    M sw = vabs(a) > vabs(b);
    V d = sel(sw, a, b);
    f.swp[k] = sw;
    f.c[k] = sel(sw, b, a);
    f.dinv[k] = 1.0 / sel(d != 0.0, d, one);
    dmin = vmin(dmin, vabs(d));
  }
}

// The Frobenius norm of the reduced matrix: the rays' squares sq_rays and those of S (NN entries; four
// independent sums).
static inline V frobenius(const V* S, i64 NN, V sq_rays) {
  const V zero = splat(0.0);
  V sq[4] = {sq_rays, zero, zero, zero};
  i64 i4 = 0;
  for (; i4 + 3 < NN; i4 += 4)
    for (int x = 0; x < 4; x++) sq[x] += S[i4 + x] * S[i4 + x];
  for (; i4 < NN; i4++) sq[0] += S[i4] * S[i4];
  return vsqrt((sq[0] + sq[1]) + (sq[2] + sq[3]));
}

// The rays eliminated: column kD of the reduced matrix becomes that of S (A's original column kept in f.colA).
template <int D>
static void eliminate_rays(Factors<D>& f, const Work<D>& w, int K, int n) {
  const V zero = splat(0.0);
  V* R = f.S;
  for (int k = 0; k < K; k++) {
    const M sw = f.swp[k];
    const V g = f.c[k] * f.dinv[k];
    V* cA = f.colA + (i64)k * n;
    for (int r = 0; r < n; r++) {
      V a = R[(i64)r * n + k * D];
      cA[r] = a;
      R[(i64)r * n + k * D] = sel(sw, -(a * g), a);
    }
    for (int i = 0; i < D; i++) {
      V cb = sel(w.onl[k], -f.C[(k * D + i) * D], zero);
      R[(i64)(k * D + i) * n + k * D] += sel(sw, cb, -(cb * g));
    }
  }
}

// LU with partial pivoting of S (N × N, row-major, in place), per lane: reciprocal pivots on the diagonal, the
// pivot row of each step in piv.  Right-looking by panels of PANEL columns: the trailing rows are updated once per
// panel, not once per column (for large K the matrix does not fit in the L1 cache: a quarter of the traffic).
// Every entry receives the same updates in the same order as one column at a time.  Returns the lanes whose
// pivots are all above 1e-13 · sc.
static M lu_panels(V* S, M* piv, int N, V sc) {
  constexpr int PANEL = 8;
  const V one = splat(1.0);
  M ok = M{} == 0;  // (all true)
  auto row = [&](int r) { return S + (i64)r * N; };
  // pivot of column `col` among rows col … N − 1, its row swapped into place (whole rows, per lane, as selects:
  // one pass per distinct pivot row); returns the reciprocal pivot
  auto pivot = [&](int col) {
    V best = vabs(row(col)[col]);
    M p = M{} + col;
    for (int r = col + 1; r < N; r++) {
      V a = vabs(row(r)[col]);
      M gt = a > best;
      best = sel(gt, a, best);
      p = gt ? (M{} + r) : p;
    }
    ok &= best > 1e-13 * sc;
    piv[col] = p;
    for (M todo = p != col; any(todo);) {
      i64 pr = col;
      for (int l = 0; l < LANES; l++)
        if (todo[l]) {
          pr = p[l];
          break;
        }
      M m = todo & (p == pr);
      V *a = row(col), *b = row((int)pr);
      for (int j = 0; j < N; j++) {
        V x = a[j], y = b[j];
        a[j] = sel(m, y, x);
        b[j] = sel(m, x, y);
      }
      todo &= ~m;
    }
    V d = row(col)[col];
    return 1.0 / sel(d != 0.0, d, one);
  };
  for (int c0 = 0; c0 < N; c0 += PANEL) {
    const int pe = c0 + PANEL < N ? c0 + PANEL : N;
    for (int c = c0; c < pe; c++) {  // the panel's columns, as one column at a time, on the panel alone
      V inv = pivot(c);
      const V* pc = row(c);
      for (int r = c + 1; r < N; r++) {
        V* rr = row(r);
        V f = rr[c] * inv;
        rr[c] = f;
        for (int j = c + 1; j < pe; j++) rr[j] -= f * pc[j];
      }
      row(c)[c] = inv;
    }
    const V* prow[PANEL];
    for (int c = c0; c < pe; c++) prow[c - c0] = row(c);
    for (int k = c0 + 1; k < pe; k++)  // the trailing part of the panel's rows (pivot rows of the next ones)
      update_row(row(k), prow, k - c0, c0, pe, N);
    for (int r = pe; r < N; r++) update_row(row(r), prow, pe - c0, c0, pe, N);  // the trailing rows
  }
  return ok;
}

// A factorisation record in e.R2, with pivots in e.piv2, at (s, λ): the reduced matrix assembled, its rays
// eliminated into S, then S's LU factors.  use_weak: lanes whose weakly active cones and rays are taken as inactive.
// Returns the lanes where it is nonsingular (the rays' pivots and S's above 1e-13 of the Frobenius norm of the
// reduced matrix).
template <int D>
static M factor(Exact<D>& e, const Work<D>& w, const V* s_l, const V* lam_l, const V* s_q, const V* lam_q,
                M use_weak) {
  const int K = e.K, n = e.n;
  Factors<D> f(e.R2, K);
  V sq_rays = splat(0.0), dmin = splat(__builtin_inf());
  assemble<D>(f, w, K, n, s_l, lam_l, s_q, lam_q, use_weak, sq_rays, dmin);
  const V sc = frobenius(f.S, (i64)n * n, sq_rays);
  eliminate_rays<D>(f, w, K, n);
  const M ok = (dmin > 1e-13 * sc) & lu_panels(f.S, e.piv2, n, sc);
  *e.scale2 = sc;
  return ok;
}

// Keep the new factors (R2, piv2) in the lanes of `mask`.
template <int D>
static void keep_factors(Exact<D>& e, M mask) {
  if (!any(~mask)) {  // (all lanes: the new factors become the current ones, the old ones scratch)
    V* R = e.R;
    M* piv = e.piv;
    e.R = e.R2, e.piv = e.piv2, e.R2 = R, e.piv2 = piv;
    return;
  }
  const i64 F = Exact<D>::F(e.K);
  for (i64 i = 0; i < F; i++) e.R[i] = sel(mask, e.R2[i], e.R[i]);
  for (int i = 0; i < e.n; i++) e.piv[i] = mask ? e.piv2[i] : e.piv[i];
}

// Solve S y = y (or Sᵀ y = y) in place with the factors in e.R, e.piv (y: n).
template <int D>
static void lu_solve(const Exact<D>& e, V* y, bool transpose) {
  const int N = e.n;
  const V* R = e.R;
  auto swap = [&](int i) {
    for (int l = 0; l < LANES; l++) {
      i64 p = e.piv[i][l];
      if (p != i) {
        double t = y[i][l];
        y[i][l] = y[p][l];
        y[p][l] = t;
      }
    }
  };
  if (!transpose) {
    for (int i = 0; i < N; i++) swap(i);
    for (int i = 0; i < N; i++)
      for (int r = i + 1; r < N; r++) y[r] -= R[(i64)r * N + i] * y[i];
    for (int i = N - 1; i >= 0; i--) {
      V xi = y[i] * R[(i64)i * N + i];
      y[i] = xi;
      for (int r = 0; r < i; r++) y[r] -= R[(i64)r * N + i] * xi;
    }
  } else {
    for (int i = 0; i < N; i++) {
      V xi = y[i] * R[(i64)i * N + i];
      y[i] = xi;
      for (int k = i + 1; k < N; k++) y[k] -= R[(i64)i * N + k] * xi;
    }
    for (int i = N - 1; i >= 0; i--)
      for (int k = 0; k < i; k++) y[k] -= R[(i64)i * N + k] * y[i];
    for (int i = N - 1; i >= 0; i--) swap(i);
  }
}

// Solve the reduced system (or its transpose) in place, y: N = n + K (rows / unknowns: contacts' n, rays' K), by
// S and the ray rows (see the top of this file).
template <int D>
static void reduced_solve(const Exact<D>& e, const Work<D>& w, V* y, bool transpose) {
  const int K = e.K, n = e.n;
  const V zero = splat(0.0);
  Factors<D> f(e.R, K);
  auto colB = [&](int k, int i) { return sel(w.onl[k], -f.C[(k * D + i) * D], zero); };
  if (!transpose) {
    for (int k = 0; k < K; k++) {  // the rays' right-hand sides into the contacts' rows
      const M sw = f.swp[k];
      const V gd = y[n + k] * f.dinv[k];
      if (any(sw)) {
        const V* cA = f.colA + (i64)k * n;
        const V gs = sel(sw, gd, zero);
        for (int r = 0; r < n; r++) y[r] -= cA[r] * gs;
      }
      for (int i = 0; i < D; i++) y[k * D + i] -= sel(sw, zero, colB(k, i) * gd);
    }
    lu_solve(e, y, false);
    for (int k = 0; k < K; k++) {  // the eliminated unknowns from the ray rows
      const M sw = f.swp[k];
      V u = y[k * D], v = (y[n + k] - f.c[k] * u) * f.dinv[k];
      y[k * D] = sel(sw, v, u);
      y[n + k] = sel(sw, u, v);
    }
  } else {
    for (int k = 0; k < K; k++) {
      const M sw = f.swp[k];
      V h1 = sel(sw, y[n + k], y[k * D]), h2 = sel(sw, y[k * D], y[n + k]);
      y[k * D] = h1 - f.c[k] * (h2 * f.dinv[k]);
      y[n + k] = h2;
    }
    lu_solve(e, y, true);
    for (int k = 0; k < K; k++) {
      const M sw = f.swp[k];
      V t = zero;
      for (int i = 0; i < D; i++) t += colB(k, i) * y[k * D + i];
      if (any(sw)) {
        const V* cA = f.colA + (i64)k * n;
        V a[4] = {zero, zero, zero, zero};  // (four independent sums)
        int r = 0;
        for (; r + 3 < n; r += 4)
          for (int x = 0; x < 4; x++) a[x] += cA[r + x] * y[r + x];
        for (; r < n; r++) a[0] += cA[r] * y[r];
        t = sel(sw, (a[0] + a[1]) + (a[2] + a[3]), t);
      }
      y[n + k] = (y[n + k] - t) * f.dinv[k];
    }
  }
}

// Solve K x = b (transpose: Kᵀ x = b) with the factors at hand.  b, x: (b_stat (n), b_ray (K), b_cone (n)).
template <int D>
static void solve_full(Exact<D>& e, const Work<D>& w, const V* b, V* x, bool transpose) {
  const int K = e.K, n = e.n, N = e.N;
  const V zero = splat(0.0);
  V* y = e.y;
  const V* C = Factors<D>(e.R, K).C;
  if (!transpose) {
    for (int k = 0; k < K; k++)
      for (int i = 0; i < D; i++) {
        V t = b[N + k * D + i];
        for (int j = 0; j < D; j++) t += C[(k * D + i) * D + j] * b[k * D + j];
        y[k * D + i] = sel(w.on[k], t, b[k * D + i]);
      }
    for (int k = 0; k < K; k++) y[n + k] = b[n + k];
    reduced_solve(e, w, y, false);
    for (int i = 0; i < N; i++) x[i] = y[i];
    matvec<false>(n, w.P, y, [&](int r) { return -b[r]; }, [&](int r, V t) { x[N + r] = t; });
    for (int k = 0; k < K; k++)
      for (int i = 0; i < D; i++) {
        int r = k * D + i;
        V t = x[N + r];
        if (i == 0) t -= sel(w.onl[k], y[n + k], zero);
        x[N + r] = sel(w.on[k], t, b[N + r]);
      }
  } else {
    for (int i = 0; i < N; i++) y[i] = b[i];
    for (int k = 0; k < K; k++)
      for (int i = 0; i < D; i++) {
        int r = k * D + i;
        V g = sel(w.on[k], b[N + r], zero);
        for (int j = 0; j < n; j++) y[j] += w.P[(i64)r * n + j] * g;
        if (i == 0) y[n + k] -= sel(w.onl[k], g, zero);
      }
    reduced_solve(e, w, y, true);
    for (int k = 0; k < K; k++) {
      x[n + k] = y[n + k];
      for (int i = 0; i < D; i++) {
        int r = k * D + i;
        V t = -b[N + r];
        for (int j = 0; j < D; j++) t += C[(k * D + j) * D + i] * y[k * D + j];
        x[r] = sel(w.on[k], t, y[r]);
        x[N + r] = sel(w.on[k], y[r], b[N + r]);
      }
    }
  }
}

// The Newton step from (z, s_l, λ_l, s_q, λ_q), whose residuals are in e.r_*, e.comp_*, with the factors in e.R:
// the step into e.dx, the trial point into e.zt, e.slt, e.llt, e.sqt, e.lqt.
template <int D>
static void newton_trial(Exact<D>& e, const Work<D>& w, const V* z, const V* s_l, const V* lam_l, const V* s_q,
                         const V* lam_q, M use_weak) {
  const int K = e.K, n = e.n, N = e.N;
  const V zero = splat(0.0);
  // right-hand side: −residuals, complementarity linearised with its primal residual
  V* b = e.x;
  for (int i = 0; i < n; i++) b[i] = -e.r_z[i];
  for (int k = 0; k < K; k++) {
    V ray = -e.comp_l[k] + lam_l[k] * e.r_l[k];
    b[n + k] = sel(w.onl[k], sel(use_weak & weak_ray(s_l[k], lam_l[k]), -lam_l[k], ray), zero);
    M weak = use_weak & weak_cone<D>(s_q + k * D, lam_q + k * D);
    for (int i = 0; i < D; i++) {
      int r = k * D + i;
      V lr;
      if (i == 0) {
        lr = zero;
        for (int j = 0; j < D; j++) lr += lam_q[k * D + j] * e.r_q[k * D + j];
      } else {
        lr = lam_q[k * D] * e.r_q[r] + lam_q[r] * e.r_q[k * D];
      }
      b[N + r] = sel(w.on[k], sel(weak, -lam_q[r], -e.comp_q[r] + lr), zero);
    }
  }
  V* dx = e.dx;
  solve_full(e, w, b, dx, false);
  for (int i = 0; i < n; i++) e.zt[i] = z[i] + dx[i];
  for (int k = 0; k < K; k++) {
    M ul = w.onl[k];
    e.llt[k] = sel(ul, lam_l[k] + dx[n + k], lam_l[k]);
    e.slt[k] = sel(ul, s_l[k] - e.r_l[k] + dx[k * D], s_l[k]);
    for (int i = 0; i < D; i++) {
      int r = k * D + i;
      e.lqt[r] = sel(w.on[k], lam_q[r] + dx[N + r], lam_q[r]);
      e.sqt[r] = sel(w.on[k], s_q[r] - e.r_q[r] + dx[r], s_q[r]);
    }
  }
}

// Newton steps (at most `steps` factorisations) from the iterate in w (z, s_l, …) in the lanes of `run`; the
// factors are reused for chord steps while the residual falls by 100× per step.  Returns the exact KKT residual of
// each lane's returned point.
template <int D>
static V polish_pass(Exact<D>& e, Work<D>& w, int steps, M use_weak, M run) {
  const int K = e.K, n = e.n, N = e.N;
  const V zero = splat(0.0);
  V* z = w.zb;
  V *s_l = w.slb, *lam_l = w.llb, *s_q = w.sqb, *lam_q = w.lqb;
  V res = kkt_residual(w, w.h_l, z, s_l, lam_l, s_q, lam_q, e.r_z, e.r_l, e.r_q, e.comp_l, e.comp_q);
  M factored = M{} != 0;  // (all false)
  V n_factor = zero;
  for (int iter = 0; iter < 4 * steps; iter++) {
    run &= ~(res <= POLISHED);
    M fresh = run & ~factored;
    M out_of_steps = fresh & (n_factor >= (double)steps);
    run &= ~out_of_steps;
    fresh &= ~out_of_steps;
    if (!any(run)) break;
    if (any(fresh)) {
      M ok = factor(e, w, s_l, lam_l, s_q, lam_q, use_weak);
      keep_factors(e, fresh | ~run);  // (the lanes that have stopped need no factors)
      n_factor += sel(fresh, splat(1.0), zero);
      run &= ~(fresh & ~ok);  // singular: stop (the caller's weak pass or rerun handles it)
      fresh &= ok;
      factored |= fresh;
      if (!any(run)) break;
    }
    newton_trial(e, w, z, s_l, lam_l, s_q, lam_q, use_weak);
    const V* dx = e.dx;
    V nw = kkt_residual(w, w.h_l, e.zt, e.slt, e.llt, e.sqt, e.lqt, e.t_z, e.t_l, e.t_q, e.tc_l, e.tc_q);
    M acc = run & (nw < res);
    M rej = run & ~acc;
    factored &= ~rej;  // a chord step that does not help: refactorise at the current point
    factored &= ~(acc & ~fresh & (nw > 1e-2 * res));
    auto commit = [&](M m, V value) {  // the trial point becomes the current one in the lanes of m
      res = sel(m, value, res);
      take_point(m, n, K, z, s_l, lam_l, s_q, lam_q, e.zt, e.slt, e.llt, e.sqt, e.lqt);
      take_point(m, n, K, e.r_z, e.r_l, e.comp_l, e.r_q, e.comp_q, e.t_z, e.t_l, e.tc_l, e.t_q, e.tc_q);  // (its residuals)
    };
    commit(acc, nw);
    // a fresh Newton step that does not help: shorter steps along it (halved up to DAMPING times; the next step
    // from new factors), else done.  A shorter step must lower the residual itself, not only relative to ‖z‖∞
    // (which a step along an unbounded ray would do by growing z).
    M damp = rej & fresh & (res <= DAMP_BELOW);
    V alpha = splat(1.0);
    const V now = res * size_of(z, n);
    for (int h = 0; h < DAMPING && any(damp); h++) {  // (the full step's own formulas are kept above, bit for bit)
      alpha *= 0.5;
      for (int i = 0; i < n; i++) e.zt[i] = z[i] + alpha * dx[i];
      for (int k = 0; k < K; k++) {
        M ul = w.onl[k];
        e.llt[k] = sel(ul, lam_l[k] + alpha * dx[n + k], lam_l[k]);
        e.slt[k] = sel(ul, s_l[k] + alpha * (dx[k * D] - e.r_l[k]), s_l[k]);
        for (int i = 0; i < D; i++) {
          int r = k * D + i;
          e.lqt[r] = sel(w.on[k], lam_q[r] + alpha * dx[N + r], lam_q[r]);
          e.sqt[r] = sel(w.on[k], s_q[r] + alpha * (dx[r] - e.r_q[r]), s_q[r]);
        }
      }
      V nd = kkt_residual(w, w.h_l, e.zt, e.slt, e.llt, e.sqt, e.lqt, e.t_z, e.t_l, e.t_q, e.tc_l, e.tc_q);
      M better = damp & (nd * size_of(e.zt, n) < now);
      commit(better, nd);
      factored &= ~better;
      damp &= ~better;
    }
    run &= ~damp;
  }
  return res;
}

// Polyhedral cones (D ≤ 2: the rays, and the 2-d cone, which is the orthant of its eigenvalues s0 ± s1): the best
// iterate moved onto the faces it points to — of each complementary pair (slack and multiplier of a ray; per
// eigenvalue, those of a cone) the smaller set to 0 — and one Newton step from there.  On the right faces the
// complementarity's second-order term is 0 along them, so that step solves the problem to rounding.  Where it does
// not reach rounding level (POLISHED), once more with the choices flipped whose kept member the step made negative;
// where that does not either, the iterate is restored and polishing goes on from it.  (Until then w's loop state
// holds the iterate and w.e_l, w.e_q the choices: both free after the interior-point method.)
template <int D>
static void faces_step(Exact<D>& e, Work<D>& w, M run) {
  const int K = e.K, n = e.n;
  const V zero = splat(0.0), half = splat(0.5);
  const M none = M{} != 0, all = M{} == 0;
  M *bind_l = (M*)w.e_l, *bind_q = (M*)w.e_q;  // the slack is the 0 of the pair (rays; cones' u = s0 + s1, v = s0 − s1)
  take_point(all, n, K, w.z, w.s_l, w.lam_l, w.s_q, w.lam_q, w.zb, w.slb, w.llb, w.sqb, w.lqb);
  for (int k = 0; k < K; k++) {
    bind_l[k] = w.llb[k] > w.slb[k];
    if (D == 2) {
      const V *s = w.sqb + 2 * k, *l = w.lqb + 2 * k;
      bind_q[2 * k] = l[0] + l[1] > s[0] + s[1];
      bind_q[2 * k + 1] = l[0] - l[1] > s[0] - s[1];
    }
  }
  M todo = run;
  for (int attempt = 0; attempt < 2 && any(todo); attempt++) {
    for (int k = 0; k < K; k++) {  // the iterate moved onto the chosen faces, in the lanes of todo
      M ul = todo & w.onl[k];
      w.slb[k] = sel(ul & bind_l[k], zero, sel(ul, w.s_l[k], w.slb[k]));
      w.llb[k] = sel(ul & ~bind_l[k], zero, sel(ul, w.lam_l[k], w.llb[k]));
      if (D == 2) {
        const V *s0 = w.s_q + 2 * k, *l0 = w.lam_q + 2 * k;
        V *s = w.sqb + 2 * k, *l = w.lqb + 2 * k;
        const M bu = bind_q[2 * k], bv = bind_q[2 * k + 1], on = todo & w.on[k];
        V su = sel(bu, zero, s0[0] + s0[1]), sv = sel(bv, zero, s0[0] - s0[1]);
        V lu = sel(bu, l0[0] + l0[1], zero), lv = sel(bv, l0[0] - l0[1], zero);
        s[0] = sel(on, half * (su + sv), s[0]), s[1] = sel(on, half * (su - sv), s[1]);
        l[0] = sel(on, half * (lu + lv), l[0]), l[1] = sel(on, half * (lu - lv), l[1]);
      }
    }
    kkt_residual(w, w.h_l, w.zb, w.slb, w.llb, w.sqb, w.lqb, e.r_z, e.r_l, e.r_q, e.comp_l, e.comp_q);
    M ok = factor(e, w, w.slb, w.llb, w.sqb, w.lqb, none);
    keep_factors(e, all);
    newton_trial(e, w, w.zb, w.slb, w.llb, w.sqb, w.lqb, none);
    V nw = kkt_residual(w, w.h_l, e.zt, e.slt, e.llt, e.sqt, e.lqt, e.t_z, e.t_l, e.t_q, e.tc_l, e.tc_q);
    // (at rounding level relative to the iterate's size: a step far along a flat direction is not taken)
    M good = todo & ok & (nw * size_of(e.zt, n) <= POLISHED * size_of(w.z, n));
    take_point(good, n, K, w.zb, w.slb, w.llb, w.sqb, w.lqb, e.zt, e.slt, e.llt, e.sqt, e.lqt);
    todo &= ok & ~good;
    const V neg = -1e-13 * size_of(e.zt, n);  // (below 0 by more than rounding)
    M flipped = none;
    for (int k = 0; k < K; k++) {
      M f = todo & w.onl[k] & (bind_l[k] ? (e.llt[k] < neg) : (e.slt[k] < neg));
      bind_l[k] ^= f, flipped |= f;
      if (D == 2) {
        const V *s = e.sqt + 2 * k, *l = e.lqt + 2 * k;
        M& bu = bind_q[2 * k];
        M& bv = bind_q[2 * k + 1];
        M fu = todo & w.on[k] & (bu ? (l[0] + l[1] < neg) : (s[0] + s[1] < neg));
        M fv = todo & w.on[k] & (bv ? (l[0] - l[1] < neg) : (s[0] - s[1] < neg));
        bu ^= fu, bv ^= fv, flipped |= fu | fv;
      }
    }
    todo &= flipped;
    run &= ~good;
  }
  // the iterate back where no step reached rounding level
  take_point(run, n, K, w.zb, w.slb, w.llb, w.sqb, w.lqb, w.z, w.s_l, w.lam_l, w.s_q, w.lam_q);
}

// Polish the best iterates of w in the lanes of `run`: a pass with every cone as it is, then, where
// that does not reach rounding level, a pass with the weakly active cones taken as inactive (which keeps only
// what lowers the residual).
template <int D>
static V polish(Exact<D>& e, Work<D>& w, int steps, M run) {
  if (D <= 2) faces_step(e, w, run);
  V r = polish_pass(e, w, steps, M{} != 0, run);
  M again = run & (r > 1e-15);
  if (any(again)) {
    V r2 = polish_pass(e, w, steps, M{} == 0, again);
    r = sel(again, r2, r);
  }
  return r;
}

// Kᵀ[u; v] = [g; 0] for the elements of one group gathered into w (P, on, onl; the solution in zb, slb, …):
// returns the lanes where K is nonsingular, with the weakly active cones of singular lanes taken as inactive
// (the dense form: exact._kkt_matrix); u in e.dx[0..n), the rays' v in e.dx[n..n+K).
template <int D>
static M adjoint(Exact<D>& e, Work<D>& w, const V* g) {
  const int n = e.n, N = e.N;
  M all = M{} == 0, none = M{} != 0;
  M ok = factor(e, w, w.slb, w.llb, w.sqb, w.lqb, none);
  keep_factors(e, all);
  M bad = ~ok;
  if (any(bad)) {
    M ok2 = factor(e, w, w.slb, w.llb, w.sqb, w.lqb, all);
    keep_factors(e, bad);
    ok |= bad & ok2;
  }
  for (int i = 0; i < N + n; i++) e.x[i] = i < n ? g[i] : splat(0.0);
  solve_full(e, w, e.x, e.dx, true);
  return ok;
}

}  // namespace NS
