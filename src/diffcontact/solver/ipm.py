"""Batched primal-dual interior-point method for many small contact cone QPs (no autograd).

Standard form, per batch element (all contacts of dimension d, K contacts, n = K·d variables):

    minimise ½ zᵀPz + cᵀz   subject to   z_n,i ≥ l_i  and  ‖z_t,i‖ ≤ z_n,i   for every active contact i,

i.e. G z + s = h with s in the product of K non-negative rays and (if d ≥ 2) K second-order cones, where
G z = (−z_n,i ; −z_i) and h = (−l_i ; 0).  Inactive contacts have no cones and P = I, c = 0 there, so z = 0.

The method is Mehrotra's predictor–corrector with Nesterov–Todd scaling (as in CVXOPT's coneqp).  The
reduced Newton matrix H = P + GᵀW⁻²G is P plus a d×d block per contact; it is positive definite even when P is
singular, and one Cholesky factor serves both directions of an iteration.  The iterations run in a compiled
kernel (``kernel.py``), one problem per batch element; this module wraps it and prepares, on demand, the
factor of H at the solution that the implicit backward pass needs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from diffcontact.solver import cones, kernel
from diffcontact.solver.linalg import SPDFactor

CONVERGED, INACCURATE, MAX_ITER, NUMERICAL, UNBOUNDED = (
    kernel.CONVERGED,
    kernel.INACCURATE,
    kernel.MAX_ITER,
    kernel.NUMERICAL,
    kernel.UNBOUNDED,
)


@dataclass
class IPMResult:
    """Solution, status, and what the backward pass needs.  Shapes: B batch, K contacts, n = K·d."""

    z: torch.Tensor  # (B, n)
    status: torch.Tensor  # (B,) int64, codes above
    iterations: torch.Tensor  # (B,) int64
    residual: torch.Tensor  # (B,) scaled KKT residual of the returned iterate
    P: torch.Tensor  # (B, n, n)
    s_l: torch.Tensor  # (B, K) slack and dual of the rays
    lam_l: torch.Tensor
    s_q: torch.Tensor  # (B, K, d) slack and dual of the second-order cones
    lam_q: torch.Tensor
    on: torch.Tensor  # (B, K) bool, cones in use
    on_l: torch.Tensor  # (B, K) bool, rays in use
    _factor: SPDFactor | None = field(default=None, repr=False)

    @property
    def w2_lin(self) -> torch.Tensor:
        """(B, K) W⁻² of the rays (λ/s), 0 where unused."""
        return self.on_l * self.lam_l / self.s_l

    @property
    def factor(self) -> SPDFactor:
        """Factorisation of H = P + GᵀW⁻²G at the returned iterate (built on first use)."""
        if self._factor is None:
            self._factor = SPDFactor(newton_matrix(self))
        return self._factor


def newton_matrix(r: IPMResult) -> torch.Tensor:
    """H = P + GᵀW⁻²G with the symmetric NT scaling of the returned (s, λ): (B, n, n).

    The backward pass needs this symmetric scaling: the accumulated W of the iterations is only determined up
    to a Lorentz transformation, which changes WᵀW in the rotational (tangent-to-the-cone) directions.
    """
    B, K = r.on.shape
    d = r.s_q.shape[-1]
    blocks = torch.zeros(B, K, d, d, dtype=r.P.dtype)
    blocks[..., 0, 0] = r.w2_lin
    if d > 1:
        _, w_inv = cones.SocNTScaling(r.s_q, r.lam_q).matrices()
        w2 = w_inv @ w_inv.mT
        if d == 3:
            w2 = _fix_rotation(w2, r.s_q, r.lam_q)
        blocks = blocks + r.on[..., None, None] * w2
    H = r.P.clone()
    idx = torch.arange(K)
    Hv = H.view(B, K, d, K, d)
    Hv[:, idx, :, idx, :] += blocks.permute(1, 0, 2, 3)
    return H


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
    polish_steps: int = 3,
) -> IPMResult:
    """Solve the batch in standard form (see module docstring).

    P: (B, n, n) symmetric PSD; c: (B, n); lower: (B, K) ≥ 0; on: (B, K) bool, contacts whose second-order
    cone is used (d ≥ 2); on_l: (B, K) bool, contacts whose ray z_n ≥ lower is used; float64.
    The data are expected scaled to order one (see ``problem.py``); ``tol`` bounds the KKT residual relative
    to max(1, ‖z‖∞).
    """
    arrays = kernel.solve_batch(
        np.ascontiguousarray(P.numpy()),
        np.ascontiguousarray(c.numpy()),
        np.ascontiguousarray(lower.numpy()),
        np.ascontiguousarray(on.numpy()),
        np.ascontiguousarray(on_l.numpy()),
        d,
        tol,
        acceptable_tol,
        max_iter,
        polish_steps,
    )
    z, s_l, lam_l, s_q, lam_q, status, iterations, residual = (torch.from_numpy(a) for a in arrays)
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


def _fix_rotation(w2: torch.Tensor, s: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Set W⁻² in the direction that rotates the tangential part of a 3-D cone to its limit ‖λ_t‖/‖s_t‖.

    At a sliding contact s and λ lie on opposite rays of the cone boundary and turn together, so the
    linearised complementarity gives ds_rot = −(‖s_t‖/‖λ_t‖)·dλ_rot.  The NT scaling of an iterate that is not
    exactly centred gets this ratio only roughly; it is the one entry the backward pass is sensitive to.
    w2: (..., 3, 3); s, lam: (..., 3).
    """
    st = s[..., 1:]
    u = st / st.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    v = torch.zeros_like(s)
    v[..., 1] = -u[..., 1]
    v[..., 2] = u[..., 0]
    target = lam[..., 1:].norm(dim=-1) / st.norm(dim=-1).clamp_min(1e-300)
    current = (v * (w2 @ v.unsqueeze(-1)).squeeze(-1)).sum(-1)
    ok = (st.norm(dim=-1) > 0) & torch.isfinite(target)
    delta = torch.where(ok, target - current, torch.zeros_like(target))
    return w2 + delta[..., None, None] * v.unsqueeze(-1) * v.unsqueeze(-2)
