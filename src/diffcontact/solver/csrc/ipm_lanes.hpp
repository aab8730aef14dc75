// Interior-point method for many small contact cone QPs, W problems at a time in the lanes of SIMD vectors.
//
// The problem is stated in kernel.py.  The method: Mehrotra's predictor–corrector with Nesterov–Todd scaling of the
// second-order cones kept as d×d matrices and updated multiplicatively, one step of iterative refinement of every
// Newton direction near the solution, the best iterate kept, stalls detected.  The problems of a group run in lockstep:
// every operation acts on W problems at once, a problem that has finished stops being updated (its best iterate is
// kept) and the group ends when all have.  Per-contact switches (a ray or cone in use or not) are lane masks.
//
// Included once per instruction set by lanes_*.cpp with LANES (vector width) and NS (namespace) defined.
// No standard headers: the translation units switch the target ISA with a pragma first, and functions from
// headers compiled for another target could not be inlined here.

namespace NS {

typedef double V __attribute__((vector_size(8 * LANES)));
typedef long long M __attribute__((vector_size(8 * LANES)));

static inline V splat(double x) { return V{} + x; }
static inline V vsqrt(V x) {
  V r;
  for (int l = 0; l < LANES; l++) r[l] = __builtin_sqrt(x[l]);
  return r;
}
static inline V vabs(V x) { return x < 0.0 ? -x : x; }
// max / min that keep a NaN of either argument (a NaN must reach the finiteness test)
static inline V vmax(V a, V b) { return (a != a) ? a : (a >= b ? a : b); }
static inline V vmin(V a, V b) { return (a != a) ? a : (a <= b ? a : b); }
static inline bool any(M m) {
  for (int l = 0; l < LANES; l++)
    if (m[l]) return true;
  return false;
}
static inline M finite(V x) {
  M r;
  for (int l = 0; l < LANES; l++) r[l] = __builtin_isfinite(x[l]) ? -1 : 0;
  return r;
}
static inline V sel(M m, V a, V b) { return m ? a : b; }
static inline V sel(M m, V a, double b) { return m ? a : splat(b); }
static inline V sel(M m, double a, V b) { return m ? splat(a) : b; }

// max(1, ‖z‖∞) (z: n), the scale the residuals are relative to.
static inline V size_of(const V* z, int n) {
  V m = splat(1.0);
  for (int i = 0; i < n; i++) m = vmax(m, vabs(z[i]));
  return m;
}

// The point (z, s_l, λ_l, s_q, λ_q; n and K vectors) set to (z2, …) in the lanes of m.
static inline void take_point(M m, int n, int K, V* z, V* s_l, V* lam_l, V* s_q, V* lam_q, const V* z2,
                              const V* s_l2, const V* lam_l2, const V* s_q2, const V* lam_q2) {
  for (int i = 0; i < n; i++) {
    z[i] = sel(m, z2[i], z[i]);
    s_q[i] = sel(m, s_q2[i], s_q[i]);
    lam_q[i] = sel(m, lam_q2[i], lam_q[i]);
  }
  for (int k = 0; k < K; k++) {
    s_l[k] = sel(m, s_l2[k], s_l[k]);
    lam_l[k] = sel(m, lam_l2[k], lam_l[k]);
  }
}

extern "C" int posix_memalign(void** ptr, __SIZE_TYPE__ alignment, __SIZE_TYPE__ size);
extern "C" void free(void* ptr);

// Work arrays of one group (lane vectors), carved from one aligned buffer.
template <int D>
struct Work {
  int K, n;
  V *P, *c, *Hb, *L;  // Hb: H's diagonal blocks (factor)
  V *z, *r_z, *b_z, *dz, *dz2, *A_dz, *rhs;
  V *s_l, *lam_l, *lt_l, *w2l, *r_l, *h_l, *w2t_l, *ds_l, *dl_l, *e_l, *ec_l, *rc_l, *A_dsl, *A_dll;
  V *s_q, *lam_q, *lt_q, *r_q, *u_q, *t_q, *w2t_q, *dst_q, *dlt_q, *e_q, *ec_q, *rc_q, *A_dsq, *A_dlq;
  V *Wq, *Wqi, *w2q;
  V *zb, *slb, *llb, *sqb, *lqb;  // best iterate
  M *onl, *on;

  static i64 size(int K) {  // in vectors
    i64 n = (i64)K * D;
    return 4 * n * n + 9 * n + 16 * (i64)K + 16 * n + 3 * n * D + 2 * (i64)K;
  }
  void carve(V* buf, int K_) {
    K = K_;
    n = K * D;
    V* p = buf;
    auto take = [&p](i64 m) {
      V* r = p;
      p += m;
      return r;
    };
    P = take(n * n), Hb = take(n * D), L = take(n * n);
    c = take(n), z = take(n), r_z = take(n), b_z = take(n), dz = take(n), dz2 = take(n), A_dz = take(n);
    rhs = take(n), zb = take(n);
    V** kv[] = {&s_l, &lam_l, &lt_l, &w2l, &r_l, &h_l, &w2t_l, &ds_l,
                &dl_l, &e_l,   &ec_l, &rc_l, &A_dsl, &A_dll, &slb, &llb};
    for (V** a : kv) *a = take(K);
    V** qv[] = {&s_q, &lam_q, &lt_q, &r_q, &u_q, &t_q, &w2t_q, &dst_q,
                &dlt_q, &e_q, &ec_q, &rc_q, &A_dsq, &A_dlq, &sqb, &lqb};
    for (V** a : qv) *a = take(n);
    Wq = take(n * D), Wqi = take(n * D), w2q = take(n * D);
    onl = (M*)take(K);
    on = (M*)take(K);
    (void)take(n * n);  // (size(): 4n² leaves room)
  }
};

// Σ_j P[i][j]·x[j] (n × n, row-major) added to (SUB: subtracted from) init(i), passed to out(i, value) for every
// row i; four rows at a time (four independent sums: a single one waits on the latency of each multiply-add), each
// summed in the order of j as alone.
template <bool SUB, class Init, class Out>
static inline void matvec(int n, const V* P, const V* x, Init init, Out out) {
  int i = 0;
  for (; i + 3 < n; i += 4) {
    const V *p0 = P + (i64)i * n, *p1 = p0 + n, *p2 = p1 + n, *p3 = p2 + n;
    V t0 = init(i), t1 = init(i + 1), t2 = init(i + 2), t3 = init(i + 3);
    for (int j = 0; j < n; j++) {
      V xj = x[j];
      if (SUB) {
        t0 -= p0[j] * xj, t1 -= p1[j] * xj, t2 -= p2[j] * xj, t3 -= p3[j] * xj;
      } else {
        t0 += p0[j] * xj, t1 += p1[j] * xj, t2 += p2[j] * xj, t3 += p3[j] * xj;
      }
    }
    out(i, t0), out(i + 1, t1), out(i + 2, t2), out(i + 3, t3);
  }
  for (; i < n; i++) {
    const V* p0 = P + (i64)i * n;
    V t = init(i);
    for (int j = 0; j < n; j++) {
      if (SUB)
        t -= p0[j] * x[j];
      else
        t += p0[j] * x[j];
    }
    out(i, t);
  }
}

// H = P + GᵀW⁻²G read entry by entry: P off the contacts' diagonal blocks, Hb (K × D × D) on them (no copy of P).
template <int D>
struct HMatrix {
  const V* P;
  const V* Hb;
  int n;
  V operator()(int i, int j) const {
    const int k = i / D;
    return k == j / D ? Hb[(k * D + i % D) * D + j % D] : P[(i64)i * n + j];
  }
};

// Rows i … i + R − 1 of the Cholesky factor below a panel of W columns j0 … j0 + W − 1 (cholesky, below): each
// entry t = H_ij − Σ_k L_ik L_jk with k in order, then times the panel's reciprocal diagonal.  The W·R sums are
// independent (in registers: W, R are compile-time constants); within the panel, a column's entries are subtracted
// from the later columns' sums as soon as they are known (the same terms in the same order, without a chain of
// dependent multiply-adds per entry).
template <int W, int R, class Hm>
static inline void cholesky_rows(int n, int j0, int i, const Hm& h, V* L, const V* inv) {
  const V* Lc[W];
  for (int c = 0; c < W; c++) Lc[c] = L + (i64)(j0 + c) * n;
  V* Li[R];
  V t[R][W];
  for (int r = 0; r < R; r++) {
    Li[r] = L + (i64)(i + r) * n;
    for (int c = 0; c < W; c++) t[r][c] = h(i + r, j0 + c);
  }
  for (int k = 0; k < j0; k++) {
    V a[R];
    for (int r = 0; r < R; r++) a[r] = Li[r][k];
    for (int c = 0; c < W; c++) {
      V b = Lc[c][k];
      for (int r = 0; r < R; r++) t[r][c] -= a[r] * b;
    }
  }
  for (int c = 0; c < W; c++) {  // within the panel: each column's entries, then their terms in the later columns
    V x[R];
    for (int r = 0; r < R; r++) {
      x[r] = t[r][c] * inv[c];
      Li[r][j0 + c] = x[r], L[(i64)(j0 + c) * n + i + r] = x[r];
    }
    for (int c2 = c + 1; c2 < W; c2++) {
      V b = Lc[c2][j0 + c];
      for (int r = 0; r < R; r++) t[r][c2] -= x[r] * b;
    }
  }
}

// The panel of columns j0 … j0 + W − 1 of the Cholesky factor: its own rows (the sums over the columns before the
// panel for all W columns of a row at once, those right of the diagonal dropped; then column by column within the
// panel), then the rows below it, ROWS at a time (two with 32 vector registers, else one).
template <int W, class Hm>
static inline void cholesky_panel(int n, int j0, const Hm& h, V* L, M& ok) {
  constexpr int ROWS = LANES >= 8 ? 2 : 1;
  V pt[W][W], inv[W];
  for (int r = 0; r < W; r++) {
    const V* Lr = L + (i64)(j0 + r) * n;
    V t[W];
    for (int c = 0; c < W; c++) t[c] = h(j0 + r, j0 + c);
    for (int k = 0; k < j0; k++) {
      V a = Lr[k];
      for (int c = 0; c < W; c++) t[c] -= a * L[(i64)(j0 + c) * n + k];
    }
    for (int c = 0; c < W; c++) pt[r][c] = t[c];
  }
  for (int c = 0; c < W; c++) {
    const int j = j0 + c;
    V* Lj = L + (i64)j * n;
    V s = pt[c][c];
    for (int k = j0; k < j; k++) s -= Lj[k] * Lj[k];
    ok &= (s > 0.0);
    inv[c] = 1.0 / vsqrt(s > 0.0 ? s : 1.0);
    Lj[j] = inv[c];
    for (int r = c + 1; r < W; r++) {
      V* Li = L + (i64)(j0 + r) * n;
      V t = pt[r][c];
      for (int k = j0; k < j; k++) t -= Li[k] * Lj[k];
      V x = t * inv[c];
      Li[j] = x, Lj[j0 + r] = x;
    }
  }
  int i = j0 + W;
  for (; i + ROWS <= n; i += ROWS) cholesky_rows<W, ROWS>(n, j0, i, h, L, inv);
  for (; i < n; i++) cholesky_rows<W, 1>(n, j0, i, h, L, inv);
}

// Cholesky factor of H (n × n, read through h(i, j), lower triangle) into L (layout: factor below the diagonal, its
// transpose above, reciprocal diagonal).  Returns the lanes where H is positive definite.  By panels of 8 columns:
// each row below a panel is read once for all of its columns (for large K the factor does not fit in the L1 cache),
// with independent sums in registers; every entry is computed by the same operations in the same order as one
// column at a time (t = H_ij − Σ_k L_ik L_jk, k in order).
template <class Hm>
static inline M cholesky(int n, const Hm& h, V* L) {
  M ok = (M{} == 0);
  for (int j0 = 0; j0 < n; j0 += 8) {
    switch (n - j0 >= 8 ? 8 : n - j0) {
      case 8: cholesky_panel<8>(n, j0, h, L, ok); break;
      case 7: cholesky_panel<7>(n, j0, h, L, ok); break;
      case 6: cholesky_panel<6>(n, j0, h, L, ok); break;
      case 5: cholesky_panel<5>(n, j0, h, L, ok); break;
      case 4: cholesky_panel<4>(n, j0, h, L, ok); break;
      case 3: cholesky_panel<3>(n, j0, h, L, ok); break;
      case 2: cholesky_panel<2>(n, j0, h, L, ok); break;
      default: cholesky_panel<1>(n, j0, h, L, ok); break;
    }
  }
  return ok;
}

static inline void chol_solve(int n, const V* L, const V* b, V* x) {
  for (int i = 0; i < n; i++) x[i] = b[i];
  for (int i = 0; i < n; i++) {
    V xi = x[i] * L[i * n + i];
    x[i] = xi;
    for (int j = i + 1; j < n; j++) x[j] -= L[i * n + j] * xi;
  }
  for (int i = n - 1; i >= 0; i--) {
    V xi = x[i] * L[i * n + i];
    x[i] = xi;
    for (int j = 0; j < i; j++) x[j] -= L[i * n + j] * xi;
  }
}

// H = P + GᵀW⁻²G and its factor, with one diagonal shift of the lanes where it is not positive definite.
template <int D>
static M factor(Work<D>& w, const V* w2l, const V* w2q, M run) {
  const int n = w.n, K = w.K;
  for (int k = 0; k < K; k++)  // H's diagonal blocks (the rest of H is P)
    for (int i = 0; i < D; i++)
      for (int j = 0; j < D; j++) {
        V t = w.P[(i64)(k * D + i) * n + k * D + j];
        if (i == 0 && j == 0) t += sel(w.onl[k], w2l[k], 0.0);
        if (D > 1) t += sel(w.on[k], w2q[(k * D + i) * D + j], 0.0);
        w.Hb[(k * D + i) * D + j] = t;
      }
  const HMatrix<D> h{w.P, w.Hb, n};
  M ok = cholesky(n, h, w.L);
  if (!any(run & ~ok)) return ok;
  V m = splat(1.0);
  for (int i = 0; i < n; i++) m = vmax(m, vabs(h(i, i)));
  for (double shift = 1e-13; shift <= 1e-7 && any(run & ~ok); shift *= 1e3) {
    for (int i = 0; i < n; i++) w.Hb[i * D + i % D] += sel(ok, splat(0.0), shift * m);
    ok = cholesky(n, h, w.L);
  }
  return ok;
}

// Largest α ≥ 0 keeping x + α dx in the cone (x inside); inf if none.
template <int D>
static inline V soc_max_step(const V* x, const V* dx) {
  V a = dx[0] * dx[0], b = x[0] * dx[0], r = splat(0.0);
  for (int i = 1; i < D; i++) {
    a -= dx[i] * dx[i];
    b -= x[i] * dx[i];
    r += x[i] * x[i];
  }
  r = vsqrt(r);
  V c = vmax((x[0] - r) * (x[0] + r), splat(0.0));
  V disc = b * b - a * c;
  M none = disc < -1e-12 * (b * b + vabs(a * c));
  V sq = vsqrt(vmax(disc, splat(0.0)));
  V qq = b >= 0.0 ? -(b + sq) : -(b - sq);
  const V inf = splat(__builtin_inf());
  V r1 = qq / sel(a != 0.0, a, 1.0);
  V best = sel((a != 0.0) & (r1 > 0.0), r1, inf);
  V r2 = c / sel(qq != 0.0, qq, 1.0);
  best = sel((qq != 0.0) & (r2 > 0.0) & (r2 < best), r2, best);
  return sel(none, inf, best);
}

// NT scaling of one cone: W, Wi (D×D) with W λ = W⁻¹ s.
template <int D>
static inline void nt_scaling(const V* s, const V* lam, V* W, V* Wi) {
  V rs = splat(0.0), rl = splat(0.0);
  for (int i = 1; i < D; i++) {
    rs += s[i] * s[i];
    rl += lam[i] * lam[i];
  }
  rs = vsqrt(rs);
  rl = vsqrt(rl);
  V sn = vsqrt(vmax((s[0] - rs) * (s[0] + rs), splat(1e-300)));
  V ln = vsqrt(vmax((lam[0] - rl) * (lam[0] + rl), splat(1e-300)));
  V dot = splat(0.0);
  for (int i = 0; i < D; i++) dot += s[i] * lam[i] / (sn * ln);
  V gamma = vsqrt(vmax((1.0 + dot) / 2.0, splat(1e-300)));
  V v[D];
  for (int i = 0; i < D; i++) v[i] = (s[i] / sn + (i == 0 ? lam[i] : -lam[i]) / ln) / (2.0 * gamma);
  v[0] += 1.0;
  V nv = vsqrt(2.0 * v[0]);
  for (int i = 0; i < D; i++) v[i] /= nv;
  V eta = vsqrt(sn / ln);
  for (int i = 0; i < D; i++)
    for (int j = 0; j < D; j++) {
      double jij = i == j ? (i == 0 ? 1.0 : -1.0) : 0.0;
      double sij = (i == 0 ? 1.0 : -1.0) * (j == 0 ? 1.0 : -1.0);
      W[i * D + j] = eta * (2.0 * v[i] * v[j] - jij);
      Wi[i * D + j] = (2.0 * sij * v[i] * v[j] - jij) / eta;
    }
}

template <int D>
static inline void jprod(const V* x, const V* y, V* out) {
  V t = splat(0.0);
  for (int i = 0; i < D; i++) t += x[i] * y[i];
  out[0] = t;
  for (int i = 1; i < D; i++) out[i] = x[0] * y[i] + y[0] * x[i];
}

// Solve P Δz + GᵀΔλ = b_z, GΔz + Δs = b_s, λ̃∘(W⁻ᵀΔs + WΔλ) = rc.
template <int D>
static void newton(Work<D>& w, const V* b_l, const V* b_q, const V* rc_l, const V* rc_q) {
  const int n = w.n, K = w.K;
  for (int i = 0; i < n; i++) w.rhs[i] = w.b_z[i];
  for (int k = 0; k < K; k++) {
    V u = rc_l[k] / w.lt_l[k];
    V t = -b_l[k] + (w.s_l[k] / w.lt_l[k]) * u;
    w.w2t_l[k] = sel(w.onl[k], w.w2l[k] * t, 0.0);
    w.rhs[k * D] += w.w2t_l[k];
    if (D > 1) {
      const V* lt = w.lt_q + k * D;
      const V* rc = rc_q + k * D;
      V* uq = w.u_q + k * D;
      V r1 = splat(0.0), det = lt[0] * lt[0];
      for (int i = 1; i < D; i++) {
        r1 += lt[i] * rc[i];
        det -= lt[i] * lt[i];
      }
      V u0 = (lt[0] * rc[0] - r1) / det;
      uq[0] = u0;
      for (int i = 1; i < D; i++) uq[i] = (rc[i] - u0 * lt[i]) / lt[0];
      const V* Wq = w.Wq + k * D * D;
      V* tq = w.t_q + k * D;
      for (int i = 0; i < D; i++) {
        V t2 = -b_q[k * D + i];
        for (int j = 0; j < D; j++) t2 += Wq[j * D + i] * uq[j];
        tq[i] = t2;
      }
      const V* w2q = w.w2q + k * D * D;
      for (int i = 0; i < D; i++) {
        V t2 = splat(0.0);
        for (int j = 0; j < D; j++) t2 += w2q[i * D + j] * tq[j];
        w.rhs[k * D + i] += sel(w.on[k], t2, 0.0);
      }
    }
  }
  chol_solve(n, w.L, w.rhs, w.dz);
  for (int k = 0; k < K; k++) {
    V g = -w.dz[k * D];
    w.dl_l[k] = sel(w.onl[k], w.w2l[k] * g + w.w2t_l[k], 0.0);
    w.ds_l[k] = sel(w.onl[k], b_l[k] - g, 0.0);
    if (D > 1) {
      V tmp[D];
      for (int i = 0; i < D; i++) tmp[i] = -w.dz[k * D + i] + w.t_q[k * D + i];
      const V* Wqi = w.Wqi + k * D * D;
      for (int i = 0; i < D; i++) {
        V t = splat(0.0);
        for (int j = 0; j < D; j++) t += Wqi[j * D + i] * tmp[j];
        w.dlt_q[k * D + i] = sel(w.on[k], t, 0.0);
        w.dst_q[k * D + i] = sel(w.on[k], w.u_q[k * D + i] - t, 0.0);
      }
    }
  }
}

// max over the cones in use of −(smallest eigenvalue of sign·s)
template <int D>
static V worst(const Work<D>& w, double sign) {
  V r = splat(-__builtin_inf());
  for (int k = 0; k < w.K; k++) {
    r = sel(w.onl[k], vmax(r, -sign * w.s_l[k]), r);
    if (D > 1) {
      V t = splat(0.0);
      for (int i = 1; i < D; i++) t += w.s_q[k * D + i] * w.s_q[k * D + i];
      r = sel(w.on[k], vmax(r, -(sign * w.s_q[k * D] - vsqrt(t))), r);
    }
  }
  return r;
}

// ---- the stages of one group's interior-point method (solve_group, below) ----
// Each is inlined into solve_group (always_inline: the compiled code, fused multiply-adds included, is that of a
// single function).

#define STAGE static inline __attribute__((always_inline))

// The loop state of one group, per lane.
struct Loop {
  M run;                  // lanes still iterating
  V degree;               // number of rays and cones in use (0: nothing to solve, z = 0)
  V best_res, best_age;   // residual of the best iterate, iterations since the last progress
  V best_inf;             // least infeasibility max(pres, dres) / zmax so far
  V zmax, gap;            // max(1, ‖z‖∞) and the duality gap of the current iterate
  V tau, step;            // centring target and step length of the current iteration
  i64 stat[LANES], its[LANES];
};

// Initial point: the minimiser with W = I (the cones replaced by their equality), shifted into the cones by
// `start_margin` plus how far it lies outside them (CVXOPT's rule).
template <int D>
STAGE void initial_point(Work<D>& w, const SolveArgs& o, Loop& s) {
  const int K = w.K, n = w.n;
  const V one = splat(1.0), zero = splat(0.0);
  s.degree = zero;
  for (int k = 0; k < K; k++) {
    s.degree += sel(w.onl[k], one, zero);
    if (D > 1) s.degree += sel(w.on[k], one, zero);
  }
  // outputs of a lane that never records an iterate (no cone in use: z = 0)
  for (int i = 0; i < n; i++) w.zb[i] = zero, w.sqb[i] = zero, w.lqb[i] = zero;
  for (int k = 0; k < K; k++) w.slb[k] = one, w.llb[k] = one;
  s.run = s.degree > 0.0;
  for (int l = 0; l < LANES; l++) s.stat[l] = s.run[l] ? MAX_ITER : CONVERGED, s.its[l] = 0;
  for (int k = 0; k < K; k++) {
    w.w2l[k] = one;
    for (int i = 0; i < D; i++)
      for (int j = 0; j < D; j++) w.w2q[(k * D + i) * D + j] = splat(i == j ? 1.0 : 0.0);
  }
  factor(w, w.w2l, w.w2q, s.run);
  for (int i = 0; i < n; i++) w.b_z[i] = -w.c[i];
  for (int k = 0; k < K; k++) w.b_z[k * D] -= w.h_l[k];  // + Gᵀh, G = −e_n on the ray (h_l = 0 if unused)
  chol_solve(n, w.L, w.b_z, w.z);
  for (int k = 0; k < K; k++) {
    w.s_l[k] = sel(w.onl[k], w.h_l[k] + w.z[k * D], one);
    for (int i = 0; i < D; i++) w.s_q[k * D + i] = sel(w.on[k], w.z[k * D + i], i == 0 ? one : zero);
  }
  V shift_s = worst(w, 1.0), shift_l = worst(w, -1.0);
  V add_s = sel(shift_s >= -1e-8, o.start_margin + shift_s, zero);
  V add_l = sel(shift_l >= -1e-8, o.start_margin + shift_l, zero);
  for (int k = 0; k < K; k++) {
    w.lam_l[k] = sel(w.onl[k], -w.s_l[k] + add_l, one);
    w.s_l[k] = sel(w.onl[k], w.s_l[k] + add_s, one);
    for (int i = 0; i < D; i++) {
      V* sq = w.s_q + k * D + i;
      V* l = w.lam_q + k * D + i;
      V e = i == 0 ? one : zero;
      M use = w.on[k];  // (never set for D = 1)
      *l = sel(use, -*sq + (i == 0 ? add_l : zero), e);
      *sq = sel(use, *sq + (i == 0 ? add_s : zero), e);
    }
  }
}

// NT scaling of the cones at the initial point, and the scaled point λ̃ = W λ.
template <int D>
STAGE void initial_scaling(Work<D>& w) {
  if (D > 1)
    for (int k = 0; k < w.K; k++) {
      nt_scaling<D>(w.s_q + k * D, w.lam_q + k * D, w.Wq + k * D * D, w.Wqi + k * D * D);
      for (int i = 0; i < D; i++) {
        V t = splat(0.0);
        for (int j = 0; j < D; j++) t += w.Wq[k * D * D + i * D + j] * w.lam_q[k * D + j];
        w.lt_q[k * D + i] = t;
      }
    }
}

// Residuals of the current iterate into w.r_z, r_l, r_q; s.zmax and s.gap; the primal and dual residuals
// (max norms) into pres, dres.  Returns the scaled residual max(pres, dres, gap) / zmax.
template <int D>
STAGE V residuals(Work<D>& w, Loop& s, V& pres, V& dres) {
  const int K = w.K, n = w.n;
  const bool soc = D > 1;
  const V zero = splat(0.0);
  matvec<false>(n, w.P, w.z, [&](int i) { return w.c[i]; }, [&](int i, V t) { w.r_z[i] = t; });
  const V zmax = size_of(w.z, n);
  V gap = zero;
  pres = zero;
  for (int k = 0; k < K; k++) {
    w.r_z[k * D] -= sel(w.onl[k], w.lam_l[k], zero);
    w.r_l[k] = sel(w.onl[k], -w.z[k * D] + w.s_l[k] - w.h_l[k], zero);
    pres = vmax(pres, vabs(w.r_l[k]));
    gap += sel(w.onl[k], w.s_l[k] * w.lam_l[k], zero);
    for (int i = 0; i < D; i++) {
      int r = k * D + i;
      if (soc) w.r_z[r] -= sel(w.on[k], w.lam_q[r], zero);
      w.r_q[r] = soc ? sel(w.on[k], -w.z[r] + w.s_q[r], zero) : zero;
      pres = vmax(pres, vabs(w.r_q[r]));
      if (soc) gap += sel(w.on[k], w.s_q[r] * w.lam_q[r], zero);
    }
  }
  dres = zero;
  for (int i = 0; i < n; i++) dres = vmax(dres, vabs(w.r_z[i]));
  s.zmax = zmax, s.gap = gap;
  return vmax(vmax(pres, dres), gap) / zmax;
}

// Keep the best iterate; end the lanes that converged (res ≤ ipm_tol), diverged (‖z‖∞ > 1e12: UNBOUNDED), went
// non-finite or stalled: 5 iterations without progress, where progress is a better iterate or an infeasibility
// (inf = max(pres, dres) / zmax) at most 0.9 of the least so far.  (From a start far below the solution's size the
// gap grows for several iterations while the infeasibility falls: a rope of 50 nodes, 52 stretch and bend limits
// in use, has its best residual at iteration 3 and converges at 14.)
template <int D>
STAGE void keep_best(Work<D>& w, const SolveArgs& o, Loop& s, V res, V inf) {
  const int K = w.K, n = w.n;
  s.run &= finite(res);  // a non-finite residual ends the lane (status by its best iterate, in finish)
  M better = s.run & (res < s.best_res);
  if (any(better)) {
    s.best_res = sel(better, res, s.best_res);
    take_point(better, n, K, w.zb, w.slb, w.llb, w.sqb, w.lqb, w.z, w.s_l, w.lam_l, w.s_q, w.lam_q);
  }
  M feasible = s.run & (inf <= 0.9 * s.best_inf);
  s.best_inf = sel(s.run & (inf < s.best_inf), inf, s.best_inf);
  s.best_age = sel(better | feasible, splat(0.0), s.best_age + 1.0);
  M conv = s.run & (res <= o.ipm_tol);
  M unb = s.run & ~conv & (s.zmax > 1e12);
  for (int l = 0; l < LANES; l++) {
    if (conv[l]) s.stat[l] = CONVERGED;
    if (unb[l]) s.stat[l] = UNBOUNDED;
  }
  s.run &= ~conv & ~unb & (s.best_age < 5.0);
}

// Scaling and factorisation: W⁻² of the rays and cones at the current iterate, H = P + GᵀW⁻²G and its Cholesky
// factor; a lane whose H is not positive definite even after a shift ends (NUMERICAL).
template <int D>
STAGE void scale_and_factor(Work<D>& w, Loop& s) {
  for (int k = 0; k < w.K; k++) {
    w.w2l[k] = w.lam_l[k] / w.s_l[k];
    w.lt_l[k] = vsqrt(w.s_l[k] * w.lam_l[k]);
    if (D > 1) {
      const V* Wi = w.Wqi + k * D * D;
      for (int i = 0; i < D; i++)
        for (int j = 0; j < D; j++) {
          V t = splat(0.0);
          for (int m = 0; m < D; m++) t += Wi[i * D + m] * Wi[j * D + m];
          w.w2q[(k * D + i) * D + j] = t;
        }
    }
  }
  M ok = factor(w, w.w2l, w.w2q, s.run);
  M bad = s.run & ~ok;
  for (int l = 0; l < LANES; l++)
    if (bad[l]) s.stat[l] = NUMERICAL;
  s.run &= ok;
}

// Iterative refinement of the direction in w.dz2, A_ds*, A_dl* (near the solution, where W is badly
// conditioned): one more Newton solve on the residuals of the unscaled equations, added in the lanes of `refine`.
template <int D>
STAGE void refine_direction(Work<D>& w, M refine) {
  const int K = w.K, n = w.n;
  const V zero = splat(0.0);
  matvec<true>(n, w.P, w.dz, [&](int i) { return -w.r_z[i]; }, [&](int i, V t) { w.b_z[i] = t; });
  for (int k = 0; k < K; k++) {
    w.b_z[k * D] += sel(w.onl[k], w.dl_l[k], zero);
    w.e_l[k] = sel(w.onl[k], -w.r_l[k] + w.dz[k * D] - w.ds_l[k], zero);
    w.ec_l[k] = sel(w.onl[k],
                    w.rc_l[k] - w.lt_l[k] * (w.ds_l[k] * w.lt_l[k] / w.s_l[k] + w.dl_l[k] * w.s_l[k] / w.lt_l[k]),
                    zero);
    if (D > 1) {
      const V* Wq = w.Wq + k * D * D;
      const V* Wqi = w.Wqi + k * D * D;
      V t2[D], t1[D];
      for (int i = 0; i < D; i++) {
        V dlq = zero, dsq = zero;
        for (int j = 0; j < D; j++) {
          dlq += Wqi[i * D + j] * w.dlt_q[k * D + j];
          dsq += Wq[j * D + i] * w.dst_q[k * D + j];
        }
        w.b_z[k * D + i] += sel(w.on[k], dlq, zero);
        w.e_q[k * D + i] = sel(w.on[k], -w.r_q[k * D + i] + w.dz[k * D + i] - dsq, zero);
        t2[i] = w.dst_q[k * D + i] + w.dlt_q[k * D + i];
      }
      jprod<D>(w.lt_q + k * D, t2, t1);
      for (int i = 0; i < D; i++) w.ec_q[k * D + i] = sel(w.on[k], w.rc_q[k * D + i] - t1[i], zero);
    } else {
      for (int i = 0; i < D; i++) w.e_q[k * D + i] = w.ec_q[k * D + i] = zero;
    }
  }
  newton(w, w.e_l, w.e_q, w.ec_l, w.ec_q);
  for (int i = 0; i < n; i++) {
    w.dz[i] = sel(refine, w.dz[i] + w.dz2[i], w.dz2[i]);
    w.A_dsq[i] += sel(refine, w.dst_q[i], zero);
    w.A_dlq[i] += sel(refine, w.dlt_q[i], zero);
  }
  for (int k = 0; k < K; k++) {
    w.A_dsl[k] += sel(refine, w.ds_l[k], zero);
    w.A_dll[k] += sel(refine, w.dl_l[k], zero);
  }
}

// The Newton direction of the predictor (corrector = false: complementarity target 0) or of the corrector (its
// second-order term and the centring target τ) into w.A_dz, A_ds*, A_dl*.
template <int D>
STAGE void direction(Work<D>& w, const Loop& s, bool corrector, M refine) {
  const int K = w.K, n = w.n;
  const V zero = splat(0.0);
  for (int k = 0; k < K; k++) {  // complementarity right-hand side
    w.rc_l[k] = -w.lt_l[k] * w.lt_l[k] + (corrector ? s.tau - w.A_dsl[k] * w.A_dll[k] : zero);
    if (D > 1) {
      V t1[D], t2[D];
      jprod<D>(w.lt_q + k * D, w.lt_q + k * D, t1);
      if (corrector) jprod<D>(w.A_dsq + k * D, w.A_dlq + k * D, t2);
      for (int i = 0; i < D; i++)
        w.rc_q[k * D + i] = -t1[i] + (corrector ? -t2[i] + (i == 0 ? s.tau : zero) : zero);
    }
  }
  for (int i = 0; i < n; i++) w.b_z[i] = -w.r_z[i], w.e_q[i] = -w.r_q[i];  // b = −r
  for (int k = 0; k < K; k++) w.e_l[k] = -w.r_l[k];
  newton(w, w.e_l, w.e_q, w.rc_l, w.rc_q);
  for (int i = 0; i < n; i++) w.dz2[i] = w.dz[i], w.A_dsq[i] = w.dst_q[i], w.A_dlq[i] = w.dlt_q[i];
  for (int k = 0; k < K; k++) w.A_dsl[k] = w.ds_l[k], w.A_dll[k] = w.dl_l[k];
  if (any(s.run & refine)) {
    refine_direction(w, refine);
  } else {
    for (int i = 0; i < n; i++) w.dz[i] = w.dz2[i];
  }
  for (int i = 0; i < n; i++) w.A_dz[i] = w.dz[i];
}

// Step length: the largest α ≥ 0 that keeps the rays and cones (scaled: λ̃ + α·A_ds, λ̃ + α·A_dl) inside; inf if
// the direction never leaves them.
template <int D>
STAGE V step_length(const Work<D>& w) {
  V alpha = splat(__builtin_inf());
  for (int k = 0; k < w.K; k++) {
    M u = w.onl[k];
    alpha = sel(u & (w.A_dsl[k] < 0.0), vmin(alpha, -w.s_l[k] / w.A_dsl[k]), alpha);
    alpha = sel(u & (w.A_dll[k] < 0.0), vmin(alpha, -w.lam_l[k] / w.A_dll[k]), alpha);
    if (D > 1) {
      V a1 = soc_max_step<D>(w.lt_q + k * D, w.A_dsq + k * D);
      V a2 = soc_max_step<D>(w.lt_q + k * D, w.A_dlq + k * D);
      alpha = sel(w.on[k], vmin(alpha, vmin(a1, a2)), alpha);
    }
  }
  return alpha;
}

// Predictor: from the affine direction (in w) and its step length α, Mehrotra's centring target for the corrector,
// τ = σ·gap/degree with σ = (gap_aff/gap)³, gap_aff the gap the affine step would reach.
template <int D>
STAGE void predictor(const Work<D>& w, Loop& s, i64 it, V alpha) {
  const V zero = splat(0.0), one = splat(1.0);
  V a_aff = vmin(alpha, one);
  V gap_aff = zero;
  for (int k = 0; k < w.K; k++) {
    gap_aff += sel(w.onl[k], (w.s_l[k] + a_aff * w.A_dsl[k]) * (w.lam_l[k] + a_aff * w.A_dll[k]), zero);
    if (D > 1)
      for (int i = 0; i < D; i++) {
        int r = k * D + i;
        gap_aff += sel(w.on[k], (w.lt_q[r] + a_aff * w.A_dsq[r]) * (w.lt_q[r] + a_aff * w.A_dlq[r]), zero);
      }
  }
  V sg = vmin(vmax(gap_aff / vmax(s.gap, splat(1e-300)), zero), one);
  V sigma = sg * sg * sg;
  // a short last step: the iterate is badly centred, so centre more
  if (it > 0) sigma = sel(s.step < 0.5, vmax(sigma, splat(0.5)), sigma);
  s.tau = sigma * s.gap / sel(s.degree > 0.0, s.degree, one);
}

// Corrector: the step along the combined direction, 0.99 of its step length α (at most 1).
STAGE void corrector(Loop& s, V alpha) { s.step = vmin(0.99 * alpha, splat(1.0)); }

// Update: the iterate moved by the step; the cones' NT scaling updated multiplicatively (W⁺ = W_s·W with W_s the
// scaling of the scaled point) and the scaled point λ̃ recomputed.
template <int D>
STAGE void update(Work<D>& w, V step) {
  const V zero = splat(0.0);
  for (int i = 0; i < w.n; i++) w.z[i] += step * w.A_dz[i];
  for (int k = 0; k < w.K; k++) {
    w.s_l[k] += sel(w.onl[k], step * w.A_dsl[k], zero);
    w.lam_l[k] += sel(w.onl[k], step * w.A_dll[k], zero);
    if (D > 1) {
      V* Wq = w.Wq + k * D * D;
      V* Wqi = w.Wqi + k * D * D;
      V ts[D], tl[D], Ws[D * D], Wsi[D * D];
      for (int i = 0; i < D; i++) {
        V ds = zero, dl = zero;
        for (int j = 0; j < D; j++) {
          ds += Wq[j * D + i] * w.A_dsq[k * D + j];
          dl += Wqi[i * D + j] * w.A_dlq[k * D + j];
        }
        w.s_q[k * D + i] += sel(w.on[k], step * ds, zero);
        w.lam_q[k * D + i] += sel(w.on[k], step * dl, zero);
        ts[i] = w.lt_q[k * D + i] + step * w.A_dsq[k * D + i];  // W⁻ᵀs⁺
        tl[i] = w.lt_q[k * D + i] + step * w.A_dlq[k * D + i];  // Wλ⁺
      }
      nt_scaling<D>(ts, tl, Ws, Wsi);
      for (int i = 0; i < D; i++) {
        V t = zero;
        for (int j = 0; j < D; j++) t += Ws[i * D + j] * tl[j];
        w.lt_q[k * D + i] = sel(w.on[k], t, w.lt_q[k * D + i]);
      }
      V Wn[D * D], Wni[D * D];
      for (int i = 0; i < D; i++)
        for (int j = 0; j < D; j++) {
          V a = zero, b = zero;
          for (int m = 0; m < D; m++) {
            a += Ws[i * D + m] * Wq[m * D + j];
            b += Wqi[i * D + m] * Wsi[m * D + j];
          }
          Wn[i * D + j] = a;
          Wni[i * D + j] = b;
        }
      for (int i = 0; i < D * D; i++) {
        Wq[i] = sel(w.on[k], Wn[i], Wq[i]);
        Wqi[i] = sel(w.on[k], Wni[i], Wqi[i]);
      }
    }
  }
}

// One group; its data gathered into w (P, c, onl, on and low in h_l as −low).  Writes the best iterate to the
// w.*b arrays and status / iterations / residual per lane; trace[l] (T × 4 per lane, or null).
template <int D>
static void solve_group(Work<D>& w, const SolveArgs& o, i64* status, i64* iters_out, double* res_out,
                        double* const* trace) {
  Loop s;
  initial_point(w, o, s);
  initial_scaling(w);
  s.best_res = splat(__builtin_inf()), s.best_inf = s.best_res, s.best_age = splat(0.0);
  s.tau = splat(0.0), s.step = splat(0.0);
  for (i64 it = 0; it <= o.max_iter; it++) {
    V pres, dres;
    V res = residuals(w, s, pres, dres);
    if (it < o.T)
      for (int l = 0; l < LANES; l++)
        if (s.run[l] && trace[l]) {
          double* tr = trace[l] + 4 * it;
          tr[0] = pres[l], tr[1] = dres[l], tr[2] = s.gap[l], tr[3] = s.step[l];
        }
    keep_best(w, o, s, res, vmax(pres, dres) / s.zmax);
    if (it == o.max_iter || !any(s.run)) break;
    for (int l = 0; l < LANES; l++) s.its[l] += s.run[l] ? 1 : 0;
    scale_and_factor(w, s);
    if (!any(s.run)) break;
    M refine = s.gap < o.refine_tol * s.zmax;
    for (int phase = 0; phase < 2; phase++) {  // the predictor's direction, then the corrector's
      direction(w, s, phase == 1, refine);
      V alpha = step_length(w);
      if (phase == 0)
        predictor(w, s, it, alpha);
      else
        corrector(s, alpha);
    }
    update(w, s.step);
  }
  for (int l = 0; l < LANES; l++) {  // the status by the best iterate
    double r = s.best_res[l];
    if (s.stat[l] == MAX_ITER && r <= o.acceptable_tol) s.stat[l] = INACCURATE;
    if (s.degree[l] > 0.0 && !__builtin_isfinite(r)) s.stat[l] = NUMERICAL;
    status[l] = s.stat[l];
    iters_out[l] = s.its[l];
    res_out[l] = s.degree[l] > 0.0 ? r : 0.0;
  }
}

#undef STAGE

}  // namespace NS
