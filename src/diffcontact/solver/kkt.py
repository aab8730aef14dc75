"""The optimality conditions of the standard-form problem (see ``kernel.py``) linearised at a solution, as a dense
matrix: the reference for the compiled kernel's reduced solves (``csrc/exact_lanes.hpp``, which polishes the
interior-point solution and solves the adjoint of the backward pass) and the least-squares fallback of the
backward pass at a degenerate solution.

The conditions P z + c + Gᵀλ = 0, G z + s = h, s ∘ λ = 0 are linearised with arrow matrices (Jordan products),
which are nonsingular at a strictly complementary solution.  A cone whose multiplier is negligible next to its
slack ("weak": a contact exactly at a stick/slip or touch/separate switch) can be taken as inactive, which resolves
the degenerate case to one side.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffcontact.solver.status import WEAK_TOL


def contact_dims(d: int) -> tuple:
    """The ``dims`` argument of the compiled functions for contact dimension d: a tuple of length d (its length
    is part of its type, so each d is compiled on its own with the loops over a contact's components unrolled)."""
    return (0,) * d


# fast-math without the no-NaN / no-inf assumptions (the callers test for both)
_FM = {"contract", "arcp", "nsz", "afn", "reassoc"}


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _weak_ray(s, lam, weak_tol):
    """A ray whose multiplier is negligible next to its slack: inactive, or exactly at its switch."""
    return lam <= weak_tol * max(1.0, abs(s))


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _weak_cone(s, lam, dims, weak_tol):
    """A cone whose multiplier is negligible next to its slack: sticking, or exactly at stick/slip."""
    d = len(dims)
    ns = 0.0
    nl = 0.0
    for i in range(d):
        ns += s[i] * s[i]
        nl += lam[i] * lam[i]
    return math.sqrt(nl) <= weak_tol * max(1.0, math.sqrt(ns))


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _kkt_matrix(P, s_l, lam_l, s_q, lam_q, on, onl, dims, use_weak, M, weak_tol=WEAK_TOL):
    """The linearised optimality conditions K (N × N, N = n + K + K·d) in M: unknowns (dz, dλ_rays, dλ_cones), rows
    P dz + Gᵀdλ; L(λ) G-part + L(s) dλ per used cone (arrow matrices); dλ = 0-type identity rows for unused
    cones and, with ``use_weak``, for weakly active ones (``status.WEAK_TOL``), which keep their Gᵀ column.
    (The threshold is an argument, not a global: numba would freeze a global in its cache.)"""
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
        if onl[k] and not (use_weak and _weak_ray(s_l[k], lam_l[k], weak_tol)):
            M[row, k * d] = lam_l[k]
            M[row, row] = s_l[k]
        else:
            M[row, row] = 1.0
        used = on[k] and d > 1
        weak = used and use_weak and _weak_cone(s_q[k], lam_q[k], dims, weak_tol)
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
def kkt_matrix_batch(P, s_l, lam_l, s_q, lam_q, on, onl, dims, use_weak, weak_tol=WEAK_TOL):
    """The matrices K of :func:`_kkt_matrix` for a batch: (B, N, N)."""
    d = len(dims)
    B, K = s_l.shape
    N = K * d + K + K * d
    out = np.empty((B, N, N))
    for b in range(B):
        _kkt_matrix(P[b], s_l[b], lam_l[b], s_q[b], lam_q[b], on[b], onl[b], dims, use_weak, out[b], weak_tol)
    return out
