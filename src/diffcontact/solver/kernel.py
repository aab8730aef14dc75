"""Compiled kernel of the interior-point method: one small problem per batch element, in parallel (numba).

The algorithm is the one described in ``ipm.py``: Mehrotra predictor–corrector, Nesterov–Todd scaling of the
second-order cones kept as general matrices and updated multiplicatively from the well-centred scaled iterates,
one step of iterative refinement of every Newton direction, the best iterate kept, stalls detected.  Batched
tensor code pays a fixed cost per operation that dominates for problems this small; a compiled loop over the
batch pays only for the arithmetic, and each element stops as soon as it has converged.

Layout: n = K·d variables; every contact k has a ray (z_n ≥ lower, used when ``on_l[k]``) and, for d ≥ 2, a
second-order cone ‖z_t‖ ≤ z_n (used when ``on[k]``).  The interior-point method runs to 1e-5; the solution is
then polished by Newton's method on the exact conditions (``exact.py``).

The contact dimension d is passed as ``dims``, any tuple of length d (``contact_dims(d)``): a tuple's length is
part of its type, so every d gets its own compiled code in which the loops over a contact's d components are
unrolled (a quarter faster than a run-time d).
"""

from __future__ import annotations

import math
import os

import numpy as np
from numba import njit, prange

from diffcontact.solver import exact
from diffcontact.solver.exact import dual_residual, polish


def _refresh_stale_cache() -> None:
    """numba's on-disk cache checks only the time stamp of a function's own file, but this module's functions
    have ``exact.py``'s compiled in: when that file is newer, touch this one so that the cache is rebuilt."""
    try:
        if os.path.getmtime(exact.__file__) > os.path.getmtime(__file__):
            os.utime(__file__)
    except OSError:  # a read-only installation: its files are not edited either
        pass


_refresh_stale_cache()

CONVERGED, INACCURATE, MAX_ITER, NUMERICAL, UNBOUNDED = 0, 1, 2, 3, 4
IPM_TOL = 1e-5  # the interior-point method's target before polishing (measured fastest in 1e-8 … 1e-3)


# fast-math without the no-NaN / no-inf assumptions: the kernel tests for both
_FM = {"contract", "arcp", "nsz", "afn", "reassoc"}


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _soc_max_step(x, dx, dims):
    """Largest α ≥ 0 keeping x + α dx in the cone (x inside); inf if none.  x, dx: (d,)."""
    d = len(dims)
    a = dx[0] * dx[0]
    b = x[0] * dx[0]
    for i in range(1, d):
        a -= dx[i] * dx[i]
        b -= x[i] * dx[i]
    r = 0.0
    for i in range(1, d):
        r += x[i] * x[i]
    r = math.sqrt(r)
    c = max((x[0] - r) * (x[0] + r), 0.0)
    disc = b * b - a * c
    if disc < -1e-12 * (b * b + abs(a * c)):
        return np.inf
    sq = math.sqrt(max(disc, 0.0))
    qq = -(b + sq) if b >= 0 else -(b - sq)
    best = np.inf
    if a != 0.0:
        r1 = qq / a
        if r1 > 0.0:
            best = min(best, r1)
    if qq != 0.0:
        r2 = c / qq
        if r2 > 0.0:
            best = min(best, r2)
    return best


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _nt_scaling(s, lam, dims, W, Wi, v):
    """NT scaling of one cone: W, Wi (d, d) with W λ = W⁻¹ s (symmetric; W = η(2vvᵀ − J))."""
    d = len(dims)
    rs = 0.0
    rl = 0.0
    for i in range(1, d):
        rs += s[i] * s[i]
        rl += lam[i] * lam[i]
    rs = math.sqrt(rs)
    rl = math.sqrt(rl)
    sn = math.sqrt(max((s[0] - rs) * (s[0] + rs), 1e-300))
    ln = math.sqrt(max((lam[0] - rl) * (lam[0] + rl), 1e-300))
    dot = 0.0
    for i in range(d):
        dot += s[i] * lam[i] / (sn * ln)
    gamma = math.sqrt(max((1.0 + dot) / 2.0, 1e-300))
    for i in range(d):
        jl = lam[i] / ln if i == 0 else -lam[i] / ln
        v[i] = (s[i] / sn + jl) / (2.0 * gamma)
    v[0] += 1.0
    nv = math.sqrt(2.0 * v[0])
    for i in range(d):
        v[i] /= nv
    eta = math.sqrt(sn / ln)
    for i in range(d):
        for j in range(d):
            jij = (1.0 if i == 0 else -1.0) if i == j else 0.0
            W[i, j] = eta * (2.0 * v[i] * v[j] - jij)
            si = 1.0 if i == 0 else -1.0
            sj = 1.0 if j == 0 else -1.0
            Wi[i, j] = (2.0 * si * v[i] * sj * v[j] - jij) / eta


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _cholesky(H, L):
    """Cholesky factor of H into L: the factor below the diagonal, its transpose above (so that both triangular
    solves read rows), the reciprocals of its diagonal on the diagonal.  False if H is not positive definite."""
    n = H.shape[0]
    for j in range(n):
        s = H[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0):
            return False
        inv = 1.0 / math.sqrt(s)
        L[j, j] = inv
        for i in range(j + 1, n):
            t = H[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            t *= inv
            L[i, j] = t
            L[j, i] = t
    return True


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _chol_solve(L, b, x):
    """Solve H x = b with the factor of :func:`_cholesky` (b is left unchanged).

    Column-oriented: each solved component is subtracted from all the remaining ones at once, which are
    independent updates along a stored row (the dot-product form is one long chain of dependent additions)."""
    n = L.shape[0]
    for i in range(n):
        x[i] = b[i]
    for i in range(n):  # L y = b; column i of L is row i above the diagonal
        xi = x[i] * L[i, i]
        x[i] = xi
        for j in range(i + 1, n):
            x[j] -= L[i, j] * xi
    for i in range(n - 1, -1, -1):  # Lᵀ x = y; column i of Lᵀ is row i below the diagonal
        xi = x[i] * L[i, i]
        x[i] = xi
        for j in range(i):
            x[j] -= L[i, j] * xi


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _factor(P, K, dims, onl, on, w2l, w2q, H, L):
    """H = P + GᵀW⁻²G, then its Cholesky factor (with one diagonal shift on failure)."""
    d = len(dims)
    n = K * d
    for i in range(n):
        for j in range(n):
            H[i, j] = P[i, j]
    for k in range(K):
        if onl[k]:
            H[k * d, k * d] += w2l[k]
        if on[k] and d > 1:
            for i in range(d):
                for j in range(d):
                    H[k * d + i, k * d + j] += w2q[k, i, j]
    if _cholesky(H, L):
        return True
    m = 1.0
    for i in range(n):
        m = max(m, abs(H[i, i]))
    for i in range(n):
        H[i, i] += 1e-13 * m
    return _cholesky(H, L)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _solve_one(
    P, c, low, on, onl, dims, tol, acc_tol, max_iter, margin, z_out, sl_out, ll_out, sq_out, lq_out, buf, trace
):
    """One problem.  Returns (status, iterations, residual); writes the best iterate to the *_out arrays.

    margin: how far inside the cones the starting point is put (CVXOPT's rule uses 1)."""
    d = len(dims)
    K = low.shape[0]
    n = K * d
    soc = d > 1
    # ---- work arrays: views into one buffer (no allocation per problem) ----
    off = 0
    H = buf[off : off + n * n].reshape(n, n)
    off += n * n
    L = buf[off : off + n * n].reshape(n, n)
    off += n * n
    nv = buf[off : off + 8 * n].reshape(8, n)
    off += 8 * n
    kv = buf[off : off + 20 * K].reshape(20, K)
    off += 20 * K
    kdv = buf[off : off + 22 * K * d].reshape(22, K, d)
    off += 22 * K * d
    kddv = buf[off : off + 4 * K * d * d].reshape(4, K, d, d)
    off += 4 * K * d * d
    dv = buf[off : off + 3 * d].reshape(3, d)
    off += 3 * d
    ddv = buf[off : off + 4 * d * d].reshape(4, d, d)
    z, r_z, rhs, b_z, dz, dz2, A_dz, nrhs = nv[0], nv[1], nv[2], nv[3], nv[4], nv[5], nv[6], nv[7]
    s_l, lam_l, lt_l, w2l, r_l, h_l, w2t_l, ds_l = kv[0], kv[1], kv[2], kv[3], kv[4], kv[5], kv[6], kv[7]
    dl_l, e_l, ec_l, rc_l, A_dsl, A_dll, ones_k = kv[8], kv[9], kv[10], kv[11], kv[12], kv[13], kv[14]
    s_q, lam_q, lt_q, r_q, u_q, t_q, w2t_q = kdv[0], kdv[1], kdv[2], kdv[3], kdv[4], kdv[5], kdv[6]
    dst_q, dlt_q, e_q, ec_q, rc_q, A_dsq, A_dlq = kdv[7], kdv[8], kdv[9], kdv[10], kdv[11], kdv[12], kdv[13]
    Wq, Wqi, w2q, eye_w2 = kddv[0], kddv[1], kddv[2], kddv[3]
    tmp, tmp2, vwork = dv[0], dv[1], dv[2]
    Ws, Wsi, Wn, Wni = ddv[0], ddv[1], ddv[2], ddv[3]
    for k in range(K):
        h_l[k] = 0.0
        ones_k[k] = 1.0
        for i in range(d):
            for j in range(d):
                eye_w2[k, i, j] = 1.0 if i == j else 0.0
    for k in range(K):
        if onl[k]:
            h_l[k] = -low[k]
    degree = 0.0
    for k in range(K):
        if onl[k]:
            degree += 1.0
        if on[k] and soc:
            degree += 1.0
    if degree == 0.0:
        for i in range(n):
            z_out[i] = 0.0
        return CONVERGED, 0, 0.0

    # ---- initial point: W = I ----
    _factor(P, K, dims, onl, on, ones_k, eye_w2, H, L)
    for i in range(n):
        rhs[i] = -c[i]
    for k in range(K):
        if onl[k]:
            rhs[k * d] -= h_l[k]  # + Gᵀh with G = −e_n on the ray
    _chol_solve(L, rhs, z)
    # s0 = h − Gz, λ0 = −s0, then each shifted into the interior of the cones by `margin` (CVXOPT's rule)
    for k in range(K):
        s_l[k] = h_l[k] + z[k * d] if onl[k] else 1.0
        for i in range(d):
            s_q[k, i] = z[k * d + i] if on[k] else (1.0 if i == 0 else 0.0)
    shift_s = _worst(s_l, s_q, onl, on, dims, 1.0)
    shift_l = _worst(s_l, s_q, onl, on, dims, -1.0)
    add_s = margin + shift_s if shift_s >= -1e-8 else 0.0
    add_l = margin + shift_l if shift_l >= -1e-8 else 0.0
    for k in range(K):
        if onl[k]:
            lam_l[k] = -s_l[k] + add_l
            s_l[k] += add_s
        else:
            lam_l[k] = 1.0
        for i in range(d):
            if on[k] and soc:
                lam_q[k, i] = -s_q[k, i] + (add_l if i == 0 else 0.0)
                s_q[k, i] += add_s if i == 0 else 0.0
            else:
                lam_q[k, i] = 1.0 if i == 0 else 0.0
                s_q[k, i] = 1.0 if i == 0 else 0.0
    if soc:
        for k in range(K):
            _nt_scaling(s_q[k], lam_q[k], dims, Wq[k], Wqi[k], vwork)
            for i in range(d):
                t = 0.0
                for j in range(d):
                    t += Wq[k, i, j] * lam_q[k, j]
                lt_q[k, i] = t

    best_res = np.inf
    best_age = 0
    tau = 0.0
    step = 0.0
    status = MAX_ITER
    iters = 0

    for it in range(max_iter + 1):
        # ---- residuals ----
        zmax = dual_residual(P, c, z, lam_l, lam_q, on, onl, dims, r_z)
        pres = 0.0
        gap = 0.0
        for k in range(K):
            if onl[k]:
                r_l[k] = -z[k * d] + s_l[k] - h_l[k]
                pres = max(pres, abs(r_l[k]))
                gap += s_l[k] * lam_l[k]
            else:
                r_l[k] = 0.0
            for i in range(d):
                if on[k] and soc:
                    r_q[k, i] = -z[k * d + i] + s_q[k, i]
                    pres = max(pres, abs(r_q[k, i]))
                    gap += s_q[k, i] * lam_q[k, i]
                else:
                    r_q[k, i] = 0.0
        dres = 0.0
        for i in range(n):
            dres = max(dres, abs(r_z[i]))
        res = max(max(pres, dres), gap) / zmax
        if it < trace.shape[0]:
            trace[it, 0] = pres
            trace[it, 1] = dres
            trace[it, 2] = gap
            trace[it, 3] = step
        if not math.isfinite(res):
            break
        if res < best_res:
            best_res = res
            best_age = 0
            z_out[:] = z
            sl_out[:] = s_l
            ll_out[:] = lam_l
            sq_out[:] = s_q
            lq_out[:] = lam_q
        else:
            best_age += 1
        if res <= tol:
            status = CONVERGED
            break
        if zmax > 1e12:
            status = UNBOUNDED
            break
        if best_age >= 5 or it == max_iter:
            break
        iters += 1

        # ---- scaling and factorisation ----
        for k in range(K):
            w2l[k] = lam_l[k] / s_l[k]
            lt_l[k] = math.sqrt(s_l[k] * lam_l[k])
            if soc:
                for i in range(d):
                    for j in range(d):
                        t = 0.0
                        for m in range(d):
                            t += Wqi[k, i, m] * Wqi[k, j, m]
                        w2q[k, i, j] = t
        if not _factor(P, K, dims, onl, on, w2l, w2q, H, L):
            status = NUMERICAL
            break

        for phase in range(2):
            # complementarity right-hand side
            if phase == 0:
                for k in range(K):
                    rc_l[k] = -lt_l[k] * lt_l[k]
                    if soc:
                        _jprod(lt_q[k], lt_q[k], dims, tmp)
                        for i in range(d):
                            rc_q[k, i] = -tmp[i]
            else:
                for k in range(K):
                    rc_l[k] = -lt_l[k] * lt_l[k] + tau - A_dsl[k] * A_dll[k]
                    if soc:
                        _jprod(lt_q[k], lt_q[k], dims, tmp)
                        _jprod(A_dsq[k], A_dlq[k], dims, tmp2)
                        for i in range(d):
                            rc_q[k, i] = -tmp[i] - tmp2[i] + (tau if i == 0 else 0.0)
            # first solve: b = −r
            for i in range(n):
                b_z[i] = -r_z[i]
            for k in range(K):
                e_l[k] = -r_l[k]
                for i in range(d):
                    e_q[k, i] = -r_q[k, i]
            _newton(
                P,
                L,
                K,
                dims,
                onl,
                on,
                s_l,
                lt_l,
                w2l,
                lt_q,
                Wq,
                Wqi,
                w2q,
                b_z,
                e_l,
                e_q,
                rc_l,
                rc_q,
                dz,
                ds_l,
                dl_l,
                dst_q,
                dlt_q,
                u_q,
                t_q,
                w2t_q,
                w2t_l,
                tmp,
                nrhs,
            )
            refine = gap < IPM_TOL * zmax
            # refinement (near the solution, where W is badly conditioned; past the first stage's target only):
            # residuals of the unscaled equations
            for i in range(n if refine else 0):
                t = -r_z[i]
                for j in range(n):
                    t -= P[i, j] * dz[j]
                b_z[i] = t
            for k in range(K if refine else 0):
                if onl[k]:
                    b_z[k * d] += dl_l[k]
                    e_l[k] = -r_l[k] + dz[k * d] - ds_l[k]
                    ec_l[k] = rc_l[k] - lt_l[k] * (ds_l[k] * lt_l[k] / s_l[k] + dl_l[k] * s_l[k] / lt_l[k])
                else:
                    e_l[k] = 0.0
                    ec_l[k] = 0.0
                if on[k] and soc:
                    for i in range(d):
                        dlq = 0.0
                        dsq = 0.0
                        for j in range(d):
                            dlq += Wqi[k, i, j] * dlt_q[k, j]
                            dsq += Wq[k, j, i] * dst_q[k, j]
                        b_z[k * d + i] += dlq
                        e_q[k, i] = -r_q[k, i] + dz[k * d + i] - dsq
                        tmp2[i] = dst_q[k, i] + dlt_q[k, i]
                    _jprod(lt_q[k], tmp2, dims, tmp)
                    for i in range(d):
                        ec_q[k, i] = rc_q[k, i] - tmp[i]
                else:
                    for i in range(d):
                        e_q[k, i] = 0.0
                        ec_q[k, i] = 0.0
            # keep the first solution, solve for the correction into the A_* arrays, then add
            for i in range(n):
                dz2[i] = dz[i]
            for k in range(K):
                A_dsl[k] = ds_l[k]
                A_dll[k] = dl_l[k]
                for i in range(d):
                    A_dsq[k, i] = dst_q[k, i]
                    A_dlq[k, i] = dlt_q[k, i]
            if refine:
                _newton(
                    P,
                    L,
                    K,
                    dims,
                    onl,
                    on,
                    s_l,
                    lt_l,
                    w2l,
                    lt_q,
                    Wq,
                    Wqi,
                    w2q,
                    b_z,
                    e_l,
                    e_q,
                    ec_l,
                    ec_q,
                    dz,
                    ds_l,
                    dl_l,
                    dst_q,
                    dlt_q,
                    u_q,
                    t_q,
                    w2t_q,
                    w2t_l,
                    tmp,
                    nrhs,
                )
                for i in range(n):
                    dz[i] += dz2[i]
                for k in range(K):
                    A_dsl[k] += ds_l[k]
                    A_dll[k] += dl_l[k]
                    for i in range(d):
                        A_dsq[k, i] += dst_q[k, i]
                        A_dlq[k, i] += dlt_q[k, i]
            else:
                for i in range(n):
                    dz[i] = dz2[i]
            for i in range(n):
                A_dz[i] = dz[i]
            # step length
            alpha = np.inf
            for k in range(K):
                if onl[k]:
                    if A_dsl[k] < 0:
                        alpha = min(alpha, -s_l[k] / A_dsl[k])
                    if A_dll[k] < 0:
                        alpha = min(alpha, -lam_l[k] / A_dll[k])
                if on[k] and soc:
                    alpha = min(alpha, _soc_max_step(lt_q[k], A_dsq[k], dims))
                    alpha = min(alpha, _soc_max_step(lt_q[k], A_dlq[k], dims))
            if phase == 0:
                a_aff = min(alpha, 1.0)
                gap_aff = 0.0
                for k in range(K):
                    if onl[k]:
                        gap_aff += (s_l[k] + a_aff * A_dsl[k]) * (lam_l[k] + a_aff * A_dll[k])
                    if on[k] and soc:
                        for i in range(d):
                            gap_aff += (lt_q[k, i] + a_aff * A_dsq[k, i]) * (lt_q[k, i] + a_aff * A_dlq[k, i])
                sigma = min(max(gap_aff / max(gap, 1e-300), 0.0), 1.0) ** 3
                if it > 0 and step < 0.5:
                    # the last step was short: the iterate is badly centred, so centre more (a safeguard that
                    # Mehrotra's heuristic lacks; it stops the stalls seen on ill-conditioned rope limits)
                    sigma = max(sigma, 0.5)
                tau = sigma * gap / degree
            else:
                step = min(0.99 * alpha, 1.0)
        # ---- update ----
        for i in range(n):
            z[i] += step * A_dz[i]
        for k in range(K):
            if onl[k]:
                s_l[k] += step * A_dsl[k]
                lam_l[k] += step * A_dll[k]
            if on[k] and soc:
                for i in range(d):
                    ds = 0.0
                    dl = 0.0
                    for j in range(d):
                        ds += Wq[k, j, i] * A_dsq[k, j]
                        dl += Wqi[k, i, j] * A_dlq[k, j]
                    s_q[k, i] += step * ds
                    lam_q[k, i] += step * dl
                    tmp[i] = lt_q[k, i] + step * A_dsq[k, i]  # W⁻ᵀs⁺
                    tmp2[i] = lt_q[k, i] + step * A_dlq[k, i]  # Wλ⁺
                _nt_scaling(tmp, tmp2, dims, Ws, Wsi, vwork)
                for i in range(d):
                    t = 0.0
                    for j in range(d):
                        t += Ws[i, j] * tmp2[j]
                    lt_q[k, i] = t
                for i in range(d):
                    for j in range(d):
                        a = 0.0
                        b = 0.0
                        for m in range(d):
                            a += Ws[i, m] * Wq[k, m, j]
                            b += Wqi[k, i, m] * Wsi[m, j]
                        Wn[i, j] = a
                        Wni[i, j] = b
                for i in range(d):
                    for j in range(d):
                        Wq[k, i, j] = Wn[i, j]
                        Wqi[k, i, j] = Wni[i, j]
    if status == MAX_ITER and best_res <= acc_tol:
        status = INACCURATE
    if not math.isfinite(best_res):
        status = NUMERICAL
    return status, iters, best_res


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _worst(s_l, s_q, onl, on, dims, sign):
    """max over the cones of −(smallest eigenvalue of sign·s)."""
    d = len(dims)
    worst = -np.inf
    for k in range(s_l.shape[0]):
        if onl[k]:
            worst = max(worst, -sign * s_l[k])
        if on[k] and d > 1:
            r = 0.0
            for i in range(1, d):
                r += s_q[k, i] * s_q[k, i]
            worst = max(worst, -(sign * s_q[k, 0] - math.sqrt(r)))
    return worst


@njit(cache=True, inline="always", fastmath=_FM, error_model="numpy")
def _jprod(x, y, dims, out):
    """out = x ∘ y, the Jordan product of the second-order cone."""
    d = len(dims)
    t = 0.0
    for i in range(d):
        t += x[i] * y[i]
    out[0] = t
    for i in range(1, d):
        out[i] = x[0] * y[i] + y[0] * x[i]


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _newton(
    P,
    L,
    K,
    dims,
    onl,
    on,
    s_l,
    lt_l,
    w2l,
    lt_q,
    Wq,
    Wqi,
    w2q,
    b_z,
    b_l,
    b_q,
    rc_l,
    rc_q,
    dz,
    ds_l,
    dl_l,
    dst_q,
    dlt_q,
    u_q,
    t_q,
    w2t_q,
    w2t_l,
    tmp,
    rhs,
):
    """Solve P Δz + GᵀΔλ = b_z, GΔz + Δs = b_s, λ̃∘(W⁻ᵀΔs + WΔλ) = rc (see ipm.py)."""
    d = len(dims)
    n = K * d
    soc = d > 1
    for i in range(n):
        rhs[i] = b_z[i]
    for k in range(K):
        if onl[k]:
            u = rc_l[k] / lt_l[k]
            t = -b_l[k] + (s_l[k] / lt_l[k]) * u
            w2t_l[k] = w2l[k] * t
            rhs[k * d] += w2t_l[k]
        else:
            w2t_l[k] = 0.0
        if on[k] and soc:
            # u = λ̃ \ rc (Jordan division)
            x0 = lt_q[k, 0]
            r1 = 0.0
            for i in range(1, d):
                r1 += lt_q[k, i] * rc_q[k, i]
            det = x0 * x0
            for i in range(1, d):
                det -= lt_q[k, i] * lt_q[k, i]
            u0 = (x0 * rc_q[k, 0] - r1) / det
            u_q[k, 0] = u0
            for i in range(1, d):
                u_q[k, i] = (rc_q[k, i] - u0 * lt_q[k, i]) / x0
            for i in range(d):
                t = -b_q[k, i]
                for j in range(d):
                    t += Wq[k, j, i] * u_q[k, j]
                t_q[k, i] = t
            for i in range(d):
                t = 0.0
                for j in range(d):
                    t += w2q[k, i, j] * t_q[k, j]
                w2t_q[k, i] = t
                rhs[k * d + i] += t
    _chol_solve(L, rhs, dz)
    for k in range(K):
        if onl[k]:
            g = -dz[k * d]
            dl_l[k] = w2l[k] * g + w2t_l[k]
            ds_l[k] = b_l[k] - g
        else:
            dl_l[k] = 0.0
            ds_l[k] = 0.0
        if on[k] and soc:
            for i in range(d):
                tmp[i] = -dz[k * d + i] + t_q[k, i]
            for i in range(d):
                t = 0.0
                for j in range(d):
                    t += Wqi[k, j, i] * tmp[j]
                dlt_q[k, i] = t
                dst_q[k, i] = u_q[k, i] - t
        else:
            for i in range(d):
                dlt_q[k, i] = 0.0
                dst_q[k, i] = 0.0


@njit(cache=True, parallel=True, fastmath=_FM, error_model="numpy")
def solve_batch(P, c, low, on, onl, dims, tol, acc_tol, max_iter, margin, polish_steps, trace):
    """Solve every batch element.  P: (B, n, n); c: (B, n); low, on, onl: (B, K).  float64 / bool."""
    d = len(dims)
    B, K = low.shape
    n = K * d
    z = np.zeros((B, n))
    s_l = np.ones((B, K))
    lam_l = np.ones((B, K))
    s_q = np.zeros((B, K, d))
    lam_q = np.zeros((B, K, d))
    status = np.zeros(B, dtype=np.int64)
    iters = np.zeros(B, dtype=np.int64)
    res = np.zeros(B)
    size = 2 * n * n + 8 * n + 20 * K + 22 * K * d + 4 * K * d * d + 3 * d + 4 * d * d
    n_chunks = min(B, 64)
    N = n + K + K * d
    for ch in prange(n_chunks):
        buf = np.empty(size)
        pM = np.empty((N, N))
        pbuf = np.empty(N + 5 * K + 2 * n + 4 * K * d + N * N + 2 * N)
        ipos = np.empty(4 * N, dtype=np.int64)
        for b in range(ch, B, n_chunks):
            # With polishing, the interior-point method only needs to identify the solution's structure: it
            # stops at IPM_TOL and Newton's method on the exact conditions does the rest.  Where that fails (a
            # degenerate solution) the method is run again to the full tolerance.
            passes = 2 if polish_steps > 0 and tol < IPM_TOL else 1
            for attempt in range(passes):
                tol_ipm = max(tol, IPM_TOL) if (polish_steps > 0 and attempt == 0) else tol
                st, it, r = _solve_one(
                    P[b],
                    c[b],
                    low[b],
                    on[b],
                    onl[b],
                    dims,
                    tol_ipm,
                    acc_tol,
                    max_iter,
                    margin,
                    z[b],
                    s_l[b],
                    lam_l[b],
                    s_q[b],
                    lam_q[b],
                    buf,
                    trace[b],
                )
                if polish_steps > 0 and st <= MAX_ITER:
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
                        polish_steps,
                        pM,
                        pbuf,
                        ipos,
                    )
                if st > MAX_ITER:  # numerical trouble or unbounded: reported as such
                    break
                # a first pass counts only if polishing reached rounding level: a larger residual hints at a
                # degenerate solution, which the full-tolerance pass resolves better
                if r <= (min(tol, 1e-13) if attempt < passes - 1 else tol):
                    st = CONVERGED
                    break
                st = INACCURATE if r <= acc_tol else MAX_ITER
            status[b] = st
            iters[b] = it
            res[b] = r
    return z, s_l, lam_l, s_q, lam_q, status, iters, res
