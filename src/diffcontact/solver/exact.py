"""Newton's method on the exact optimality conditions of the standard-form problem (see ``ipm.py``), compiled.

Two uses: polishing the interior-point solution to rounding accuracy (``polish``), and the adjoint solve of the
implicit backward pass (``adjoint_batch``).  Both work with the conditions P z + c + Gᵀλ = 0, G z + s = h,
s ∘ λ = 0 linearised with arrow matrices (Jordan products), which are nonsingular at a strictly complementary
solution.  A cone whose multiplier is negligible next to its slack ("weak": a contact exactly at a stick/slip or
touch/separate switch) can be taken as inactive, which resolves the degenerate case to one side.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


def contact_dims(d: int) -> tuple:
    """The ``dims`` argument of the compiled functions for contact dimension d: a tuple of length d (its length
    is part of its type, so each d is compiled on its own with the loops over a contact's components unrolled)."""
    return (0,) * d


# fast-math without the no-NaN / no-inf assumptions (the callers test for both)
_FM = {"contract", "arcp", "nsz", "afn", "reassoc"}

# per-element status codes (ipm.py), the same in the compiled interior-point kernel (lanes/ipm_lanes.hpp)
CONVERGED, INACCURATE, MAX_ITER, NUMERICAL, UNBOUNDED = 0, 1, 2, 3, 4


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _weak_ray(s, lam):
    """A ray whose multiplier is negligible next to its slack: inactive, or exactly at its switch."""
    return lam <= 1e-6 * max(1.0, abs(s))


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _weak_cone(s, lam, dims):
    """A cone whose multiplier is negligible next to its slack: sticking, or exactly at stick/slip."""
    d = len(dims)
    ns = 0.0
    nl = 0.0
    for i in range(d):
        ns += s[i] * s[i]
        nl += lam[i] * lam[i]
    return math.sqrt(nl) <= 1e-6 * max(1.0, math.sqrt(ns))


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def dual_residual(P, c, z, lam_l, lam_q, on, onl, dims, r_z):
    """r_z = P z + c + Gᵀλ (G z = (−z_n on the rays, −z on the cones)); returns max(1, ‖z‖∞)."""
    d = len(dims)
    K = lam_l.shape[0]
    n = K * d
    zmax = 1.0
    for i in range(n):
        t = c[i]
        for j in range(n):
            t += P[i, j] * z[j]
        r_z[i] = t
        zmax = max(zmax, abs(z[i]))
    for k in range(K):
        if onl[k]:
            r_z[k * d] -= lam_l[k]
        if on[k] and d > 1:
            for i in range(d):
                r_z[k * d + i] -= lam_q[k, i]
    return zmax


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _kkt_residual(P, c, h_l, on, onl, dims, z, s_l, lam_l, s_q, lam_q, r_z, r_l, r_q, comp_l, comp_q):
    """Exact KKT residuals (complementarity s∘λ = 0, not the central path); returns their max relative to
    max(1, ‖z‖∞), counting any violation of the cones as well."""
    d = len(dims)
    K = s_l.shape[0]
    n = K * d
    soc = d > 1
    worst = 0.0
    zmax = dual_residual(P, c, z, lam_l, lam_q, on, onl, dims, r_z)
    for k in range(K):
        if onl[k]:
            r_l[k] = -z[k * d] + s_l[k] - h_l[k]
            comp_l[k] = s_l[k] * lam_l[k]
            worst = max(worst, abs(r_l[k]), abs(comp_l[k]), -s_l[k], -lam_l[k])
        else:
            r_l[k] = 0.0
            comp_l[k] = 0.0
        if on[k] and soc:
            rs = 0.0
            rl = 0.0
            dot = 0.0
            for i in range(d):
                r_q[k, i] = -z[k * d + i] + s_q[k, i]
                worst = max(worst, abs(r_q[k, i]))
                dot += s_q[k, i] * lam_q[k, i]
                if i > 0:
                    rs += s_q[k, i] * s_q[k, i]
                    rl += lam_q[k, i] * lam_q[k, i]
            comp_q[k, 0] = dot
            for i in range(1, d):
                comp_q[k, i] = s_q[k, 0] * lam_q[k, i] + lam_q[k, 0] * s_q[k, i]
            for i in range(d):
                worst = max(worst, abs(comp_q[k, i]))
            worst = max(worst, math.sqrt(rs) - s_q[k, 0], math.sqrt(rl) - lam_q[k, 0])
        else:
            for i in range(d):
                r_q[k, i] = 0.0
                comp_q[k, i] = 0.0
    for i in range(n):
        worst = max(worst, abs(r_z[i]))
    return worst / zmax


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _kkt_matrix(P, s_l, lam_l, s_q, lam_q, on, onl, dims, use_weak, M):
    """The linearised optimality conditions K (N × N, N = n + K + K·d) in M: unknowns (dz, dλ_rays, dλ_cones), rows
    P dz + Gᵀdλ; L(λ) G-part + L(s) dλ per used cone (arrow matrices); dλ = 0-type identity rows for unused
    cones and, with ``use_weak``, for weakly active ones (which keep their Gᵀ column)."""
    d = len(dims)
    K = s_l.shape[0]
    n = K * d
    N = n + K + K * d
    for i in range(N):
        for j in range(N):
            M[i, j] = 0.0
    for i in range(n):
        for j in range(n):
            M[i, j] = P[i, j]
    for k in range(K):
        row = n + k
        if onl[k]:
            M[k * d, row] = -1.0
        if onl[k] and not (use_weak and _weak_ray(s_l[k], lam_l[k])):
            M[row, k * d] = lam_l[k]
            M[row, row] = s_l[k]
        else:
            M[row, row] = 1.0
        used = on[k] and d > 1
        weak = used and use_weak and _weak_cone(s_q[k], lam_q[k], dims)
        for i in range(d):
            row = n + K + k * d + i
            if used:
                M[k * d + i, row] = -1.0
            if used and not weak:
                if i == 0:
                    for j in range(d):
                        M[row, k * d + j] = lam_q[k, j]
                        M[row, n + K + k * d + j] = s_q[k, j]
                else:
                    M[row, k * d] = lam_q[k, i]
                    M[row, k * d + i] = lam_q[k, 0]
                    M[row, n + K + k * d] = s_q[k, i]
                    M[row, n + K + k * d + i] = s_q[k, 0]
            else:
                M[row, row] = 1.0


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _lu_factor(R, piv):
    """LU factorisation with partial pivoting in place: the unit lower factor below the diagonal, the upper one
    above it, the reciprocals of its diagonal on the diagonal; row i was swapped with piv[i] at step i.  False
    if R is singular (a pivot below 1e-13 of its Frobenius norm: a sum vectorises, a running max does not)."""
    N = R.shape[0]
    scale = 0.0
    for i in range(N):
        for j in range(N):
            scale += R[i, j] * R[i, j]
    scale = math.sqrt(scale)
    for col in range(N):
        p = col
        best = abs(R[col, col])
        for r in range(col + 1, N):
            if abs(R[r, col]) > best:
                best = abs(R[r, col])
                p = r
        if not (best > 1e-13 * scale):
            return False
        piv[col] = p
        if p != col:
            for j in range(N):
                t = R[col, j]
                R[col, j] = R[p, j]
                R[p, j] = t
        inv = 1.0 / R[col, col]
        for r in range(col + 1, N):
            f = R[r, col] * inv
            R[r, col] = f
            if f != 0.0:
                for j in range(col + 1, N):
                    R[r, j] -= f * R[col, j]
        R[col, col] = inv
    return True


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _lu_solve(R, piv, b, transpose):
    """Solve R x = b (or Rᵀ x = b) in place with the factors of :func:`_lu_factor`.

    Column-oriented: each solved component is subtracted from the remaining ones at once (independent
    updates, where the dot-product form is one chain of dependent additions)."""
    N = R.shape[0]
    if not transpose:
        for i in range(N):
            p = piv[i]
            if p != i:
                t = b[i]
                b[i] = b[p]
                b[p] = t
        for i in range(N):  # unit lower
            xi = b[i]
            for r in range(i + 1, N):
                b[r] -= R[r, i] * xi
        for i in range(N - 1, -1, -1):  # upper, reciprocal diagonal
            xi = b[i] * R[i, i]
            b[i] = xi
            for r in range(i):
                b[r] -= R[r, i] * xi
    else:  # Rᵀ = Uᵀ Lᵀ P
        for i in range(N):  # Uᵀ: column i of Uᵀ is row i of U right of the diagonal
            xi = b[i] * R[i, i]
            b[i] = xi
            for k in range(i + 1, N):
                b[k] -= R[i, k] * xi
        for i in range(N - 1, -1, -1):  # Lᵀ (unit): column i of Lᵀ is row i of L left of the diagonal
            xi = b[i]
            for k in range(i):
                b[k] -= R[i, k] * xi
        for i in range(N - 1, -1, -1):
            p = piv[i]
            if p != i:
                t = b[i]
                b[i] = b[p]
                b[p] = t


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _reduction(K, dims, ipos):
    """The reduction of :func:`factor_kkt` kept in ipos: returns (n, N, rowpos, colpos, ckeep) — each row's and
    column's place in the reduced matrix (−1 eliminated, −2 identity) and the kept columns in order; the LU's
    pivots follow them at ipos[3N:]."""
    n = K * len(dims)
    N = n + K + n
    return n, N, ipos[:N], ipos[N : 2 * N], ipos[2 * N : 3 * N]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def factor_kkt(M, K, dims, on, onl, work, ipos):
    """Factorise the matrix M of :func:`_kkt_matrix` for :func:`solve_factored` (M must stay unchanged).

    Exact block elimination before the dense factorisation: a used cone's multiplier enters its contact's
    stationarity rows with coefficient −1, so those rows eliminate it (a Schur complement on −I, no pivoting
    needed) and only the cone rows change; unused rays and cones are identity rows and columns.  What is left,
    N' ≤ n + K unknowns, is factorised by LU with partial pivoting.  work: float (≥ N² + 2N); ipos: int (≥ 4N).
    Returns N', or −1 if the reduced matrix is singular.
    """
    d = len(dims)
    n, N, rowpos, colpos, ckeep = _reduction(K, dims, ipos)
    soc = d > 1
    for i in range(N):
        rowpos[i] = 0
        colpos[i] = 0
    for k in range(K):
        for i in range(d):
            if on[k] and soc:  # eliminated: the stationarity row and the cone's multiplier
                rowpos[k * d + i] = -1
                colpos[n + K + k * d + i] = -1
            else:  # identity row and column
                rowpos[n + K + k * d + i] = -2
                colpos[n + K + k * d + i] = -2
        if not onl[k]:
            rowpos[n + k] = -2
            colpos[n + k] = -2
    nr = 0
    for i in range(N):
        if rowpos[i] == 0:
            rowpos[i] = nr
            nr += 1
    # the rays' multipliers first: their columns touch only their contact's rows, so eliminating them first
    # keeps the fill to those rows and leaves a dense system in dz alone
    m = 0
    for jj in range(N):
        j = n + jj if jj < K else (jj - K if jj < n + K else jj)
        if colpos[j] == 0:
            colpos[j] = m
            ckeep[m] = j
            m += 1
    R = work[: nr * nr].reshape(nr, nr)
    for i in range(N):
        if rowpos[i] >= 0:
            for t in range(nr):
                R[rowpos[i], t] = M[i, ckeep[t]]
    for k in range(K if soc else 0):  # R = K_rr + K_re K_er on the cone rows
        if not on[k]:
            continue
        for j in range(d):
            a = rowpos[n + K + k * d + j]
            for i in range(d):
                coef = M[n + K + k * d + j, n + K + k * d + i]
                if coef != 0.0:
                    for t in range(nr):
                        R[a, t] += coef * M[k * d + i, ckeep[t]]
    if not _lu_factor(R, ipos[3 * N : 3 * N + nr]):
        return -1
    return nr


@njit(cache=True, fastmath=_FM, error_model="numpy")
def solve_factored(M, K, dims, on, onl, b, work, ipos, nr, transpose):
    """Solve M x = b (or Mᵀ x = b) with the factors of :func:`factor_kkt` (which returned nr); b becomes x."""
    d = len(dims)
    n, N, rowpos, colpos, ckeep = _reduction(K, dims, ipos)
    soc = d > 1
    piv = ipos[3 * N : 3 * N + nr]
    R = work[: nr * nr].reshape(nr, nr)
    y = work[nr * nr : nr * nr + nr]
    x = work[nr * nr + nr : nr * nr + nr + N]
    if not transpose:
        for i in range(N):
            if rowpos[i] >= 0:
                y[rowpos[i]] = b[i]
        for k in range(K if soc else 0):
            if on[k]:
                for j in range(d):
                    a = n + K + k * d + j
                    for i in range(d):
                        y[rowpos[a]] += M[a, n + K + k * d + i] * b[k * d + i]
        _lu_solve(R, piv, y, False)
        for j in range(N):
            if colpos[j] >= 0:
                x[j] = y[colpos[j]]
            elif colpos[j] == -2:
                x[j] = b[j]
        for k in range(K if soc else 0):
            if on[k]:
                for i in range(d):
                    t = -b[k * d + i]
                    for tt in range(nr):
                        t += M[k * d + i, ckeep[tt]] * y[tt]
                    x[n + K + k * d + i] = t
    else:
        for t in range(nr):
            y[t] = b[ckeep[t]]
        for k in range(K if soc else 0):
            if on[k]:
                for i in range(d):
                    ge = b[n + K + k * d + i]
                    if ge != 0.0:
                        for t in range(nr):
                            y[t] += M[k * d + i, ckeep[t]] * ge
        _lu_solve(R, piv, y, True)
        for i in range(N):
            if rowpos[i] >= 0:
                x[i] = y[rowpos[i]]
            elif rowpos[i] == -2:
                x[i] = b[i]
        for k in range(K if soc else 0):
            if on[k]:
                for i in range(d):
                    t = -b[n + K + k * d + i]
                    for j in range(d):
                        a = n + K + k * d + j
                        t += M[a, n + K + k * d + i] * y[rowpos[a]]
                    x[k * d + i] = t
    for i in range(N):
        b[i] = x[i]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def solve_kkt(M, K, dims, on, onl, b, work, ipos, transpose):
    """Factorise (:func:`factor_kkt`) and solve M x = b (or Mᵀ x = b); b becomes x.  False if singular."""
    nr = factor_kkt(M, K, dims, on, onl, work, ipos)
    if nr < 0:
        return False
    solve_factored(M, K, dims, on, onl, b, work, ipos, nr, transpose)
    return True


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _polish(P, c, low, on, onl, dims, z, s_l, lam_l, s_q, lam_q, steps, M, pbuf, ipos, use_weak):
    """Newton steps (at most ``steps`` factorisations) on the exact optimality conditions from the
    interior-point solution.

    The interior-point iterate stays on the central path (s∘λ = τe); at a strictly complementary solution the
    exact conditions have a nonsingular Jacobian and Newton converges quadratically from it.  A step is kept
    only if it lowers the exact KKT residual.  Returns the exact KKT residual of the returned point and whether
    the Jacobian was singular (a degenerate solution).
    """
    d = len(dims)
    K = s_l.shape[0]
    n = K * d
    soc = d > 1
    N = n + K + K * d
    rhs = pbuf[:N]
    o = N
    h_l = pbuf[o : o + K]
    r_l = pbuf[o + K : o + 2 * K]
    comp_l = pbuf[o + 2 * K : o + 3 * K]
    slt = pbuf[o + 3 * K : o + 4 * K]
    llt = pbuf[o + 4 * K : o + 5 * K]
    o += 5 * K
    r_z = pbuf[o : o + n]
    zt = pbuf[o + n : o + 2 * n]
    o += 2 * n
    kd = K * d
    r_q = pbuf[o : o + kd].reshape(K, d)
    comp_q = pbuf[o + kd : o + 2 * kd].reshape(K, d)
    sqt = pbuf[o + 2 * kd : o + 3 * kd].reshape(K, d)
    lqt = pbuf[o + 3 * kd : o + 4 * kd].reshape(K, d)
    work = pbuf[o + 4 * kd :]
    for k in range(K):
        h_l[k] = -low[k] if onl[k] else 0.0
    res = _kkt_residual(P, c, h_l, on, onl, dims, z, s_l, lam_l, s_q, lam_q, r_z, r_l, r_q, comp_l, comp_q)
    singular = False
    nr = -1  # size of the factorisation at hand (from an earlier point), −1 if none
    n_factor = 0
    for _ in range(4 * steps):
        if res <= 1e-14:
            break
        fresh = nr < 0
        if fresh:
            if n_factor == steps:
                break
            n_factor += 1
            _kkt_matrix(P, s_l, lam_l, s_q, lam_q, on, onl, dims, use_weak, M)
            nr = factor_kkt(M, K, dims, on, onl, work, ipos)
            if nr < 0:
                singular = True
                break
        for i in range(N):
            rhs[i] = -r_z[i] if i < n else 0.0
        for k in range(K):
            if onl[k] and not (use_weak and _weak_ray(s_l[k], lam_l[k])):
                rhs[n + k] = -comp_l[k] + lam_l[k] * r_l[k]
            elif onl[k]:  # weakly active: taken as inactive, its multiplier driven to zero
                rhs[n + k] = -lam_l[k]
            if on[k] and soc:
                weak = use_weak and _weak_cone(s_q[k], lam_q[k], dims)
                for i in range(d):
                    row = n + K + k * d + i
                    if weak:
                        rhs[row] = -lam_q[k, i]
                    else:  # L(λ) dz_k + L(s) dλ = −s∘λ + L(λ) r_q
                        lr = 0.0
                        if i == 0:
                            for j in range(d):
                                lr += lam_q[k, j] * r_q[k, j]
                        else:
                            lr = lam_q[k, 0] * r_q[k, i] + lam_q[k, i] * r_q[k, 0]
                        rhs[row] = -comp_q[k, i] + lr
        # after a Newton step the factorisation is reused (a chord step: from a point this close the Jacobian
        # has barely changed, so the error still falls by orders of magnitude, at the cost of two triangular
        # solves); where it falls by less (a degenerate solution, where Newton itself converges linearly) the
        # next step refactorises at the current point
        solve_factored(M, K, dims, on, onl, rhs, work, ipos, nr, False)
        for i in range(n):
            zt[i] = z[i] + rhs[i]
        for k in range(K):
            if onl[k]:
                llt[k] = lam_l[k] + rhs[n + k]
                slt[k] = s_l[k] - r_l[k] + rhs[k * d]
            else:
                llt[k] = lam_l[k]
                slt[k] = s_l[k]
            for i in range(d):
                if on[k] and soc:
                    lqt[k, i] = lam_q[k, i] + rhs[n + K + k * d + i]
                    sqt[k, i] = s_q[k, i] - r_q[k, i] + rhs[k * d + i]
                else:
                    lqt[k, i] = lam_q[k, i]
                    sqt[k, i] = s_q[k, i]
        new = _kkt_residual(P, c, h_l, on, onl, dims, zt, slt, llt, sqt, lqt, r_z, r_l, r_q, comp_l, comp_q)
        if not (new < res):
            if fresh:
                break
            nr = -1  # (and the residuals back at the current point)
            _kkt_residual(P, c, h_l, on, onl, dims, z, s_l, lam_l, s_q, lam_q, r_z, r_l, r_q, comp_l, comp_q)
            continue
        if not fresh and new > 1e-2 * res:
            nr = -1
        res = new
        z[:] = zt
        s_l[:] = slt
        lam_l[:] = llt
        s_q[:] = sqt
        lam_q[:] = lqt
    return res, singular


@njit(cache=True, fastmath=_FM, error_model="numpy")
def polish(P, c, low, on, onl, dims, z, s_l, lam_l, s_q, lam_q, steps, M, pbuf, ipos):
    """Polish; if that does not reach rounding level (singular or slow: a contact may sit exactly at a switch),
    polish again with the weakly active cones taken as inactive (kept only if it lowers the exact residual).
    Returns the exact KKT residual of the returned point."""
    r, singular = _polish(P, c, low, on, onl, dims, z, s_l, lam_l, s_q, lam_q, steps, M, pbuf, ipos, False)
    if r > 1e-15:
        r, singular = _polish(P, c, low, on, onl, dims, z, s_l, lam_l, s_q, lam_q, steps, M, pbuf, ipos, True)
    return r


@njit(cache=True, parallel=True, fastmath=_FM, error_model="numpy")
def polish_batch(P, c, low, on, onl, dims, idx, z, s_l, lam_l, s_q, lam_q, status, res, steps, tol, acc_tol, last):
    """Polish the interior-point solutions of the elements ``idx`` in place and settle their status.

    P: (B, n, n); c: (B, n); low, on, onl: (B, K); z, s_l, lam_l, s_q, lam_q, status, res: the interior-point
    method's output (``lanes.solve``), updated at the rows ``idx``.  An element counts as converged if its exact
    KKT residual is at most ``tol`` — at most 1e-13 unless ``last``: a larger residual after a first pass hints
    at a degenerate solution, which a pass of the interior-point method to the full tolerance resolves better.
    Returns a (len(idx),) bool mask of the elements for that pass (none if ``last``).
    """
    d = len(dims)
    K = low.shape[1]
    n = K * d
    N = n + K + K * d
    m = idx.shape[0]
    again = np.zeros(m, dtype=np.bool_)
    n_chunks = min(m, 64)
    for ch in prange(n_chunks):
        M = np.empty((N, N))
        pbuf = np.empty(N + 5 * K + 2 * n + 4 * K * d + N * N + 2 * N)
        ipos = np.empty(4 * N, dtype=np.int64)
        for j in range(ch, m, n_chunks):
            b = idx[j]
            if status[b] > MAX_ITER:  # numerical trouble or unbounded: reported as such
                continue
            r = res[b]
            if steps > 0:
                r = polish(
                    P[b],
                    c[b],
                    low[b],
                    on[b],
                    onl[b],
                    dims,
                    z[b],
                    s_l[b],
                    lam_l[b],
                    s_q[b],
                    lam_q[b],
                    steps,
                    M,
                    pbuf,
                    ipos,
                )
            if r <= (tol if last else min(tol, 1e-13)):
                status[b] = CONVERGED
            else:
                status[b] = INACCURATE if r <= acc_tol else MAX_ITER
                again[j] = not last
            res[b] = r
    return again


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _adjoint_one(P, s_l, lam_l, s_q, lam_q, on, onl, dims, g, M, x, work, ipos, use_weak):
    """Kᵀ[u; v] = [g; 0] for one element into x; with ``use_weak`` its weakly active cones (a contact exactly
    at a switch) are taken as inactive, which gives a one-sided derivative.  False if K is singular."""
    d = len(dims)
    n = s_l.shape[0] * d
    N = M.shape[0]
    _kkt_matrix(P, s_l, lam_l, s_q, lam_q, on, onl, dims, use_weak, M)
    for i in range(N):
        x[i] = g[i] if i < n else 0.0
    return solve_kkt(M, s_l.shape[0], dims, on, onl, x, work, ipos, True)


@njit(cache=True, parallel=True, fastmath=_FM, error_model="numpy")
def adjoint_batch(P, s_l, lam_l, s_q, lam_q, on, onl, dims, g):
    """Solve Kᵀ[u; v] = [g; 0] per element, K the linearised optimality conditions (see ``implicit.py``).

    Returns (u: (B, n), v_l: (B, K), ok: (B,) False where K is singular even with weak cones made inactive).
    """
    d = len(dims)
    B, K = s_l.shape
    n = K * d
    N = n + K + K * d
    u = np.zeros((B, n))
    v_l = np.zeros((B, K))
    ok = np.zeros(B, dtype=np.bool_)
    n_chunks = min(B, 64)
    for ch in prange(n_chunks):
        M = np.empty((N, N))
        x = np.empty(N)
        work = np.empty(N * N + 2 * N)
        ipos = np.empty(4 * N, dtype=np.int64)
        for b in range(ch, B, n_chunks):
            for use_weak in (False, True):
                if _adjoint_one(
                    P[b], s_l[b], lam_l[b], s_q[b], lam_q[b], on[b], onl[b], dims, g[b], M, x, work, ipos, use_weak
                ):
                    ok[b] = True
                    for i in range(n):
                        u[b, i] = x[i]
                    for k in range(K):
                        v_l[b, k] = x[n + k]
                    break
    return u, v_l, ok


@njit(cache=True, fastmath=_FM, error_model="numpy")
def kkt_matrix_batch(P, s_l, lam_l, s_q, lam_q, on, onl, dims, use_weak):
    """The matrices K of :func:`_kkt_matrix` for a batch: (B, N, N)."""
    d = len(dims)
    B, K = s_l.shape
    N = K * d + K + K * d
    out = np.empty((B, N, N))
    for b in range(B):
        _kkt_matrix(P[b], s_l[b], lam_l[b], s_q[b], lam_q[b], on[b], onl[b], dims, use_weak, out[b])
    return out
