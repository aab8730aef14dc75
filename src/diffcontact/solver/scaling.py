"""The substitution f = γ·S·D·z that turns a batch of contact cone QPs into the standard form of ``lanes.py``
(compiled: one pass over the data instead of some forty small tensor operations).

Per batch element, with contact k's rows i = k·d … k·d + d − 1:

    D_i = 1 on the normal row, μ_k on the tangential ones (every friction cone becomes the unit cone);
    S_i = σ_k = A_nn,k^(−1/2) on active contacts (Jacobi scaling; the largest A_nn where A_nn is negligible), else 0;
    γ = the size of the solution, estimated contact by contact as max(lower, −q_n/A_nn), at least 1e-3 of the
        linear term S·min(D, 1)·q (that term itself when every contact separates): in units of f, without the
        tangential factor μ > 1, which made γ overestimate the solution's size by up to μ (and the kernel's test,
        relative to max(1, ‖z‖∞), in effect absolute for the small z that followed: docs/scaling.md);
    P = T A T with T = S·D, plus an identity on inactive rows and on the tangential rows of μ = 0 contacts (which
        have no cone: only the ray z_n ≥ lower remains, their z_t is pinned to 0);
    c = T q / γ;  l̂ = lower / (σ γ), lower bounds below 1e-12 of the solution's scale taken as 0.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffcontact.solver import lanes


def scale_batch(A, q, mu, lower, active, dims):
    """A: (B, n, n); q: (B, n); mu, lower: (B, K) float64; active: (B, K) bool; dims: tuple of length d.

    Returns (A_sym, P, c, l_hat, T, S, gamma, sigma, lower_scale, on_q, on_l, zero_mu): A_sym = ½(A + Aᵀ)
    (B, n, n); P (B, n, n); c, T, S (B, n); gamma (B,); sigma, l_hat, lower_scale = ∂l̂/∂lower (B, K);
    on_q (cones used), on_l (rays used), zero_mu (B, K) bool.  Run on the solver's threads (``lanes.parallel``).
    """
    B, K = mu.shape
    n = K * len(dims)
    out = (
        *(np.empty((B, n, n)) for _ in range(2)),
        *(np.empty((B, n)) for _ in range(3)),
        np.empty(B),
        *(np.empty((B, K)) for _ in range(3)),
        *(np.zeros((B, K), dtype=np.bool_) for _ in range(3)),
    )
    A_sym, P, c, T, S, gamma, sigma, l_hat, lower_scale, on_q, on_l, zero_mu = out
    lanes.parallel(lambda start, stop: _scale_range(A, q, mu, lower, active, dims, *out, start, stop), B)
    return A_sym, P, c, l_hat, T, S, gamma, sigma, lower_scale, on_q, on_l, zero_mu


@njit(cache=True, nogil=True, error_model="numpy")
def _scale_range(
    A, q, mu, lower, active, dims, A_sym, P, c, T, S, gamma, sigma, l_hat, lower_scale, on_q, on_l, zero_mu, start, stop
):
    """scale_batch for the batch elements start … stop − 1, into the given outputs."""
    d = len(dims)
    K = mu.shape[1]
    n = K * d
    for b in range(start, stop):
        As = A_sym[b]
        for i in range(n):
            for j in range(n):
                As[i, j] = 0.5 * (A[b, i, j] + A[b, j, i])
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
            for i in range(d):
                D = 1.0 if i == 0 else mu[b, k]
                S[b, k * d + i] = sg if on else 0.0
                T[b, k * d + i] = S[b, k * d + i] * D
                # (the size in units of f: a tangential factor μ > 1 would make γ overestimate it by up to μ)
                c_abs = max(c_abs, abs(S[b, k * d + i] * min(D, 1.0) * q[b, k * d + i]))
            value = max(lower[b, k] / sg, -S[b, k * d] * q[b, k * d])
            estimate = max(estimate, value if on else 0.0)
        g = max(estimate, 1e-3 * c_abs) if estimate > 0 else c_abs
        g = g if g > 0 else 1.0
        gamma[b] = g
        for k in range(K):
            on = active[b, k]
            keep = on and lower[b, k] >= 1e-12 * sigma[b, k] * g
            low = lower[b, k] if keep else 0.0
            lower_scale[b, k] = 1.0 / (sigma[b, k] * g) if keep else 0.0
            l_hat[b, k] = low / (sigma[b, k] * g) if on else 0.0
            if d > 1:
                zero_mu[b, k] = on and mu[b, k] == 0.0
                on_q[b, k] = on and not zero_mu[b, k]
                on_l[b, k] = on and (low > 0 or zero_mu[b, k])
            else:
                on_l[b, k] = on
        for i in range(n):
            c[b, i] = T[b, i] * q[b, i] / g
            for j in range(n):
                P[b, i, j] = T[b, i] * As[i, j] * T[b, j]
        for k in range(K):
            for i in range(d):
                r = k * d + i
                if not active[b, k] or (i > 0 and zero_mu[b, k]):
                    P[b, r, r] += 1.0


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
    lanes.parallel(lambda start, stop: _chain_rule_range(*args, start, stop), B)
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
                acc = slide[b, k] * u[b, k * d]
                for r in range(k * d + 1, k * d + d):
                    a_tz = 0.0  # (A T z)_r and (A T u)_r
                    a_tu = 0.0
                    for j in range(n):
                        a_tz += A[b, r, j] * T[b, j] * z[b, j]
                        a_tu += A[b, r, j] * T[b, j] * u[b, j]
                    gT = -u[b, r] * a_tz - z[b, r] * a_tu - u[b, r] * q[b, r] / g + g * z[b, r] * gf[b, r]
                    acc += gT * S[b, r]
                g_mu[b, k] = acc
        if need[3]:
            for k in range(K):
                g_lo[b, k] = lam_l[b, k] * v_l[b, k] * lower_scale[b, k] if on_l[b, k] else 0.0
    return g_A, g_q, g_mu, g_lo
