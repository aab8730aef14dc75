"""The optimality of an answer measured in the problem's own units, independently of the solver's scaling.

The kernel's convergence test is on the scaled problem (f = γ·S·D·z, ``scaling.py``), relative to max(1, ‖z‖∞).
With large friction coefficients the scaled problem is badly conditioned (P's tangential entries grow as μ²), so a
small scaled residual may not mean an accurate f: ``natural_residual`` is a guard in unscaled units.  (Until γ was
estimated without the tangential factor μ, it also overestimated the solution's size by up to μ, which made the
scaled test absolute for small solutions: the check caught those answers, 4 % at μ 10 … 1e3; now it catches none
there, docs/scaling.md.)  The natural residual

    ‖f − Π(f − α(Af + q))‖∞ / max(‖f‖∞, α‖q‖∞, max lower),   α = 1 / max_i A_ii,

with Π the projection onto the feasible set {f_n ≥ lower, ‖f_t‖ ≤ μ f_n} of each active contact (an inactive
contact's f must be 0); it is 0 exactly at the solution.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffcontact.solver.policy import POLICY

#: Friction coefficients above which an answer is also checked by its natural residual (``_solve_with_retries``):
#: below it the scaled test is accurate (worst natural residual of a usable answer 6e-11 at μ ≤ 10 measured on
#: 10,800 random problems, docs/scaling.md), and problems with μ ≤ 10 (every benchmark task) pay nothing for it.
#: Also every answer of the retry that rescales γ by the size of a stalled iterate, whatever μ.
MU_CHECKED = POLICY.mu_checked


def natural_residual(A, q, mu, lower, active, f, d: int, rows):
    """A: (B, n, n) symmetric; q, f: (B, n); mu, lower: (B, K) float64; active: (B, K) bool; rows: (m,) int64,
    the batch elements to check.  Returns (m,) the relative natural residual of f[rows] (NaN if f is not finite)."""
    out = np.empty(len(rows))
    _natural_residual(A, q, mu, lower, active, f, d, rows, out)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _natural_residual(A, q, mu, lower, active, f, d, rows, out):
    n = q.shape[1]
    K = n // d
    y = np.empty(n)
    for m in range(len(rows)):
        b = rows[m]
        a_max = 0.0
        for i in range(n):
            a_max = max(a_max, abs(A[b, i, i]))
        alpha = 1.0 / a_max if a_max > 0 else 1.0
        size = 1e-300
        for i in range(n):
            g = q[b, i]
            for j in range(n):
                g += A[b, i, j] * f[b, j]
            y[i] = f[b, i] - alpha * g
            size = max(size, abs(f[b, i]), alpha * abs(q[b, i]))
        worst = 0.0
        for k in range(K):
            r = k * d
            size = max(size, lower[b, k])
            if not active[b, k]:
                for i in range(d):
                    worst = max(worst, abs(f[b, r + i]))
                continue
            yn, t = y[r], 0.0
            for i in range(1, d):
                t += y[r + i] * y[r + i]
            t = math.sqrt(t)
            u = mu[b, k]
            if d == 1 or t <= u * yn:  # inside the cone (d = 1: the ray f_n ≥ 0)
                pn, scale = max(yn, 0.0), 1.0
            elif u * t <= -yn:  # in the polar cone
                pn, scale = 0.0, 0.0
            else:  # onto the boundary: f_n = (y_n + μt)/(1 + μ²), ‖f_t‖ = μ f_n (without overflow for large μ)
                if u > 1:
                    inv = 1.0 / u
                    pn = (yn * inv + t) * inv / (1 + inv * inv)
                    scale = (yn * inv + t) / (1 + inv * inv) / t
                else:
                    pn = (yn + u * t) / (1 + u * u)
                    scale = u * pn / t
            if pn < lower[b, k]:  # below the lower bound: onto the disk f_n = lower, ‖f_t‖ ≤ μ·lower
                pn = lower[b, k]
                scale = min(1.0, u * pn / t) if t > 0 else 1.0
            worst = max(worst, abs(f[b, r] - pn))
            for i in range(1, d):
                worst = max(worst, abs(f[b, r + i] - scale * y[r + i]))
        out[m] = worst / size
