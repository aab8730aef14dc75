"""Batched primal-dual interior-point method for many small contact cone QPs (no autograd).

Standard form, per batch element (all contacts of dimension d, K contacts, n = K·d variables):

    minimise ½ zᵀPz + cᵀz   subject to   z_n,i ≥ l_i  and  ‖z_t,i‖ ≤ z_n,i   for every active contact i,

i.e. G z + s = h with s in the product of K non-negative rays and (if d ≥ 2) K second-order cones, where
G z = (−z_n,i ; −z_i) and h = (−l_i ; 0).  Inactive contacts have no cones and P = I, c = 0 there, so z = 0.

The method is Mehrotra's predictor–corrector with Nesterov–Todd scaling (as in CVXOPT's coneqp).  The
reduced Newton matrix H = P + GᵀW⁻²G is P plus a d×d block per contact; it is positive definite even when P is
singular, and one Cholesky factor serves both directions of an iteration.  The iterations run in a compiled
kernel (``lanes.py``) that solves several problems at once in the lanes of SIMD vectors, up to the tolerance
IPM_TOL; Newton steps on the exact optimality conditions then polish the solution to rounding accuracy (in the
same kernel, ``csrc/exact_lanes.hpp``).  Where polishing does not reach rounding level (a degenerate solution),
the method is run again to the full tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from diffcontact.solver import lanes
from diffcontact.solver.status import Status

IPM_TOL = 1e-5  # the interior-point method's target before polishing (measured fastest in 1e-8 … 1e-3)

START_MARGIN = 0.1  # measured over 0.001 … 3 on random instances, K = 1 … 19, d = 2, 3
ROBUST_MARGIN = 1.0  # CVXOPT's: the retry of elements that did not converge


@dataclass
class IPMResult:
    """Solution, status, and what the backward pass needs.  Shapes: B batch, K contacts, n = K·d."""

    z: torch.Tensor  # (B, n)
    status: torch.Tensor  # (B,) int64, ``Status`` codes
    iterations: torch.Tensor  # (B,) int64
    residual: torch.Tensor  # (B,) scaled KKT residual of the returned iterate
    P: torch.Tensor  # (B, n, n)
    s_l: torch.Tensor  # (B, K) slack and dual of the rays
    lam_l: torch.Tensor
    s_q: torch.Tensor  # (B, K, d) slack and dual of the second-order cones
    lam_q: torch.Tensor
    on: torch.Tensor  # (B, K) bool, cones in use
    on_l: torch.Tensor  # (B, K) bool, rays in use


def solve_ipm(
    P: torch.Tensor,
    c: torch.Tensor,
    lower: torch.Tensor,
    on: torch.Tensor,
    on_l: torch.Tensor,
    d: int,
    *,
    tol: float = 1e-10,
    acceptable_tol: float = 1e-7,
    max_iter: int = 60,
    start_margin: float = START_MARGIN,
    polish_steps: int = 3,
    trace: np.ndarray | None = None,
) -> IPMResult:
    """Solve the batch in standard form (see module docstring).

    P: (B, n, n) symmetric PSD; c: (B, n); lower: (B, K) ≥ 0; on: (B, K) bool, contacts whose second-order
    cone is used (d ≥ 2); on_l: (B, K) bool, contacts whose ray z_n ≥ lower is used; float64.
    The data are expected scaled to order one (see ``problem.py``); ``tol`` bounds the KKT residual relative
    to max(1, ‖z‖∞).  ``start_margin``: how far inside the cones the starting point lies (CVXOPT's rule uses 1;
    the smaller default takes about half an iteration less on average, and callers retry failures with 1).
    ``trace`` (B, T, 4), if given, receives per iteration the primal and dual residuals, the gap and the step
    taken (for diagnosis).
    """
    B, K = lower.shape
    n = K * d
    data = [np.ascontiguousarray(t.numpy()) for t in (P, c, lower, on, on_l)]
    out = (
        np.zeros((B, n)),
        np.ones((B, K)),
        np.ones((B, K)),
        np.zeros((B, K, d)),
        np.zeros((B, K, d)),
        np.zeros(B, dtype=np.int64),
        np.zeros(B, dtype=np.int64),
        np.zeros(B),
    )
    if trace is None:
        trace = np.zeros((B, 0, 4))
    elif trace.dtype != np.float64 or trace.ndim != 3 or trace.shape[::2] != (B, 4) or not trace.flags.c_contiguous:
        raise ValueError(f"trace must be a C-contiguous float64 array of shape (B, T, 4) with B = {B}")
    idx = np.arange(B, dtype=np.int64)
    passes = 2 if polish_steps > 0 and tol < IPM_TOL else 1
    for attempt in range(passes):
        last = attempt == passes - 1
        lanes.solve(
            *data,
            d,
            idx,
            ipm_tol=max(tol, IPM_TOL) if polish_steps > 0 and attempt == 0 else tol,
            final_tol=tol if last else min(tol, 1e-13),
            acceptable_tol=acceptable_tol,
            max_iter=max_iter,
            start_margin=start_margin,
            refine_tol=IPM_TOL,
            polish_steps=polish_steps,
            out=out,
            trace=trace,
        )
        status = out[5][idx]
        idx = idx[(status == Status.INACCURATE) | (status == Status.MAX_ITER)]
        if not len(idx):
            break
    z, s_l, lam_l, s_q, lam_q, status, iterations, residual = (torch.from_numpy(a) for a in out)
    return IPMResult(
        z=z,
        status=status,
        iterations=iterations,
        residual=residual,
        P=P,
        s_l=s_l,
        lam_l=lam_l,
        s_q=s_q,
        lam_q=lam_q,
        on=on,
        on_l=on_l,
    )
