"""The substitution f = γ·S·D·z that turns a batch of contact cone QPs into the standard form of ``kernel.py``
(compiled: one pass over the data instead of some forty small tensor operations).

Per batch element, with contact k's rows i = k·d … k·d + d − 1:

    D_i = 1 on the normal row, μ_k on the tangential ones (every friction cone becomes the unit cone);
    S_i = σ_k = A_nn,k^(−1/2) on active contacts (Jacobi scaling; the largest A_nn where A_nn is negligible), else 0
        (the array ``S`` returned is ∂T/∂μ, below);
    γ = the size of the solution, estimated contact by contact as max(lower, −q_n/A_nn), at least 1e-3 of the
        linear term S·min(D, 1)·q (that term itself when every contact separates): in units of f, without the
        tangential factor μ > 1, which made γ overestimate the solution's size by up to μ (and the kernel's test,
        relative to max(1, ‖z‖∞), in effect absolute for the small z that followed: docs/scaling.md);
    P = T A T with T = S·D, plus an identity on inactive rows and on the tangential rows of μ = 0 contacts (which
        have no cone: only the ray z_n ≥ lower remains, their z_t is pinned to 0), i.e. on the rows where T = 0;
        formed by the kernel as it gathers a group's problems (``kernel.scaled_matrix``), not here;
    contacts with μ ≥ ``MU_FREE`` have D = 1 and no cone, only the ray z_n ≥ l̂, and a free z_t ("free"): with
        a tangential factor μ ≥ 1e4 the unit cone's z_t = f_t/(γσμ) is below the kernel's resolution next to z_n
        for a contact that sticks (its test is relative to ‖z‖∞), and such problems ended at the iteration limit
        or with gradients wrong by 100 %.  A free answer inside the cone (stick or separate) solves the problem
        with the cone exactly (the cone is inactive there, its multiplier 0); one outside it (sliding) is solved
        again with the cone and D = (1/μ, 1) on that contact (``sliding``: z_n = μ f_n/(γσ) and z_t of one size
        where ‖f_t‖ = μ f_n), ``problem._solve_with_retries``.  S is ∂T/∂μ: σ on the tangential rows of D = μ,
        −σ/μ² on the normal row of D = 1/μ, else 0;
    c = T q / γ;  l̂ = lower / (T_n γ), lower bounds below 1e-12 of the solution's scale taken as 0.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffcontact.solver import kernel
from diffcontact.solver.policy import POLICY

#: Friction coefficients from which a contact is solved free first, and again scaled for sliding where its answer
#: leaves the cone (module docstring).  Measured: at 1e6 gradients at μ 1e4 … 1e6 were wrong by up to 3e-5 relative
#: (2e-9 at 1e4); problems with μ < 1e4 are scaled as before.
MU_FREE = POLICY.mu_free
_NONE_SLIDING = np.zeros((0, 0), dtype=np.bool_)  # (no contact scaled for sliding: nothing allocated)


def scale_batch(A, q, mu, lower, active, dims, sliding=None, symmetric=None):
    """A: (B, n, n); q: (B, n); mu, lower: (B, K) float64; active: (B, K) bool; dims: tuple of length d; sliding:
    (B, K) bool or None, contacts with μ ≥ ``MU_FREE`` to scale for sliding (their cone kept) rather than free;
    symmetric: (B,) bool, where A equals its transpose exactly, if known (``flat.flat_elements``), else A is read here.

    Returns (A_sym, c, l_hat, T, S, gamma, sigma, lower_scale, on_q, on_l, zero_mu): A_sym = ½(A + Aᵀ)
    (B, n, n; A itself if symmetric); c, T, S = ∂T/∂μ (B, n); gamma (B,); sigma, l_hat, lower_scale = ∂l̂/∂lower
    (B, K); on_q (cones used), on_l (rays used), zero_mu (B, K) bool.  P = T·A_sym·T (plus the identity on the rows
    where T is 0) is formed by the kernel (``kernel.scaled_matrix``).  Run on the solver's threads
    (``kernel.parallel``).
    """
    B, K = mu.shape
    n = K * len(dims)
    if (np.count_nonzero(symmetric) == B) if symmetric is not None else _symmetric(A):
        A_sym = A
    else:
        A_sym = A + A.swapaxes(1, 2)
        A_sym *= 0.5
    e, z = np.empty, np.zeros  # (spelled out: generator expressions cost 2 µs more, a tenth of a small call)
    out = (
        *(e((B, n)), e((B, n)), e((B, n))),
        e(B),
        *(e((B, K)), e((B, K)), e((B, K))),
        *(z((B, K), dtype=np.bool_), z((B, K), dtype=np.bool_), z((B, K), dtype=np.bool_)),
    )
    c, T, S, gamma, sigma, l_hat, lower_scale, on_q, on_l, zero_mu = out
    sliding = _NONE_SLIDING if sliding is None else sliding
    kernel.parallel(lambda start, stop: _scale_range(A_sym, q, mu, lower, active, sliding, dims, *out, start, stop), B)
    return A_sym, c, l_hat, T, S, gamma, sigma, lower_scale, on_q, on_l, zero_mu


@njit(cache=True, nogil=True)
def _symmetric(A) -> bool:
    """Whether A (B, n, n) equals its transpose exactly (its symmetric part then needs no copy)."""
    B, n, _ = A.shape
    for b in range(B):
        for i in range(n):
            for j in range(i):
                if A[b, i, j] != A[b, j, i]:
                    return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _scale_range(
    A_sym, q, mu, lower, active, sliding, dims, c, T, S, gamma, sigma, l_hat, lower_scale, on_q, on_l, zero_mu, start,
    stop,
):  # fmt: skip
    """scale_batch for the batch elements start … stop − 1 (A_sym: the symmetric A), into the given outputs."""
    d = len(dims)
    K = mu.shape[1]
    n = K * d
    for b in range(start, stop):
        As = A_sym[b]
        a_max = -np.inf
        for k in range(K):
            a_max = max(a_max, As[k * d, k * d] if active[b, k] else 0.0)
        a_ref = a_max if a_max > 0 else 1.0
        estimate = -np.inf
        c_abs = 0.0
        for k in range(K):
            on = active[b, k]
            a_nn = As[k * d, k * d] if on else 0.0
            sg = 1.0 / math.sqrt(a_nn if a_nn > 1e-12 * a_ref else a_ref)
            sigma[b, k] = sg
            large = on and d > 1 and mu[b, k] >= MU_FREE
            slides = large and len(sliding) > 0 and sliding[b, k]
            for i in range(d):
                r = k * d + i
                D = (1.0 / mu[b, k] if slides else 1.0) if i == 0 else (1.0 if large else mu[b, k])
                T[b, r] = sg * D if on else 0.0
                # ∂T/∂μ: σ on the tangential rows of a cone scaled by μ, −σ/μ² on the normal row of one scaled for
                # sliding, else 0
                if i == 0:
                    S[b, r] = -sg * D / mu[b, k] if slides else 0.0
                else:
                    S[b, r] = sg if on and not large else 0.0
                # (the size in units of f: a tangential factor μ > 1 would make γ overestimate it by up to μ)
                c_abs = max(c_abs, abs(sg * min(D, 1.0) * q[b, r]) if on else 0.0)
            value = max(lower[b, k] / sg, -sg * q[b, k * d])
            estimate = max(estimate, value if on else 0.0)
        g = max(estimate, 1e-3 * c_abs) if estimate > 0 else c_abs
        g = g if g > 0 else 1.0
        gamma[b] = g
        for k in range(K):
            on = active[b, k]
            large = on and d > 1 and mu[b, k] >= MU_FREE
            free = large and not (len(sliding) > 0 and sliding[b, k])
            s_n = sigma[b, k] / mu[b, k] if large and not free else sigma[b, k]  # (T_n)
            keep = on and lower[b, k] >= 1e-12 * s_n * g
            low = lower[b, k] if keep else 0.0
            lower_scale[b, k] = 1.0 / (s_n * g) if keep else 0.0
            l_hat[b, k] = low / (s_n * g) if on else 0.0
            if d > 1:
                zero_mu[b, k] = on and mu[b, k] == 0.0
                on_q[b, k] = on and not zero_mu[b, k] and not free
                on_l[b, k] = on and (low > 0 or zero_mu[b, k] or free)
            else:
                on_l[b, k] = on
        for i in range(n):
            c[b, i] = T[b, i] * q[b, i] / g


@njit(cache=True, nogil=True)
def unscale(gamma, T, z):
    """(γ·T)⊙z (B, n) for gamma (B,), T, z (B, n): f of the scaled solution z, or γT⊙g for the adjoint's right-hand
    side (as numpy's ``gamma[:, None] * T * z``, bit for bit, in one compiled call: a µs less at B = 1)."""
    B, n = z.shape
    f = np.empty((B, n))
    for b in range(B):
        for i in range(n):
            f[b, i] = gamma[b] * T[b, i] * z[b, i]
    return f


def outside_cones(z, mu, free, d):
    """(B, K) bool: the contacts ``free`` ((B, K) bool: μ ≥ ``MU_FREE``, scaled free) whose answer z (B, n) of the
    scaled problem lies outside their cone, ‖f_t‖ > μ f_n (f = γσz on their rows)."""
    B, n = z.shape
    zk = z.reshape(B, n // d, d)
    return free & (np.linalg.norm(zk[..., 1:], axis=-1) > mu * zk[..., 0])


def chain_rule_batch(u, v_l, z, gf, A, q, T, S, gamma, lam_l, on_l, lower_scale, slide, dims, need):
    """The chain rule of the substitution, from the adjoint solution back to the data (see ``implicit.py``).

    u, z, gf (∂L/∂f), q, T, S: (B, n); v_l, lam_l, lower_scale, slide: (B, K); A: (B, n, n) the symmetrised A;
    gamma: (B,); on_l: (B, K) bool; need: (4,) bool, which of ∂L/∂A, ∂L/∂q, ∂L/∂μ, ∂L/∂lower to compute.
    Returns (g_A (B, n, n), g_q (B, n), g_mu (B, K), g_lower (B, K)); arrays not needed have shape (0, …).
    In z-space ∂L/∂P = −½(u zᵀ + z uᵀ), ∂L/∂c = −u, ∂L/∂l̂ = λ_l v_l; P = T A T, c = T q/γ, f = γ T z.
    """
    B, K = v_l.shape
    n = K * len(dims)
    grads = (
        np.empty((B if need[0] else 0, n, n)),
        np.empty((B if need[1] else 0, n)),
        np.zeros((B if need[2] else 0, K)),  # (stays 0 for d = 1: no friction)
        np.empty((B if need[3] else 0, K)),
    )
    args = (u, v_l, z, gf, A, q, T, S, gamma, lam_l, on_l, lower_scale, slide, dims, need, *grads)
    kernel.parallel(lambda start, stop: _chain_rule_range(*args, start, stop), B)
    return grads


@njit(cache=True, nogil=True, error_model="numpy")
def _chain_rule_range(
    u, v_l, z, gf, A, q, T, S, gamma, lam_l, on_l, lower_scale, slide, dims, need, g_A, g_q, g_mu, g_lo, start, stop
):
    """chain_rule_batch for the batch elements start … stop − 1, into the given outputs."""
    d = len(dims)
    K = v_l.shape[1]
    n = K * d
    for b in range(start, stop):
        g = gamma[b]
        if need[0]:
            for i in range(n):
                tu = T[b, i] * u[b, i]
                tz = T[b, i] * z[b, i]
                for j in range(n):
                    g_A[b, i, j] = -0.5 * (tu * T[b, j] * z[b, j] + tz * T[b, j] * u[b, j])
        if need[1]:
            for i in range(n):
                g_q[b, i] = -T[b, i] * u[b, i] / g
        if need[2] and d > 1:
            for k in range(K):
                r0 = k * d
                acc = slide[b, k] * u[b, r0]
                if S[b, r0] != 0.0 or S[b, r0 + 1] != 0.0 or S[b, r0 + d - 1] != 0.0:
                    # (A T z)_r and (A T u)_r of the contact's rows r0 + i (the last again for d = 2), six
                    # independent sums (one at a time waits on the latency of each addition), each in the order of j
                    ra, rb, rc = r0, r0 + 1, r0 + d - 1
                    za, zb, zc, ua, ub, uc = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                    for j in range(n):
                        tj, zj, uj = T[b, j], z[b, j], u[b, j]
                        a, bb, c = A[b, ra, j] * tj, A[b, rb, j] * tj, A[b, rc, j] * tj
                        za += a * zj
                        ua += a * uj
                        zb += bb * zj
                        ub += bb * uj
                        zc += c * zj
                        uc += c * uj
                    for i in range(d):
                        r = r0 + i
                        if S[b, r] == 0.0:  # (T_r does not depend on μ)
                            continue
                        a_tz = za if i == 0 else (zb if i == 1 else zc)
                        a_tu = ua if i == 0 else (ub if i == 1 else uc)
                        gT = -u[b, r] * a_tz - z[b, r] * a_tu - u[b, r] * q[b, r] / g + g * z[b, r] * gf[b, r]
                        acc += gT * S[b, r]
                g_mu[b, k] = acc
        if need[3]:
            for k in range(K):
                g_lo[b, k] = lam_l[b, k] * v_l[b, k] * lower_scale[b, k] if on_l[b, k] else 0.0
    return g_A, g_q, g_mu, g_lo
