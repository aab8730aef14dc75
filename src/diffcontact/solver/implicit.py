"""Implicit differentiation of the standard-form cone QP at its solution (one autograd Function).

The optimality conditions P z + c + Gᵀλ = 0, G z + s = h, s ∘ λ = 0 (Jordan product per cone) are
linearised at the returned iterate, with ds = dh − G dz eliminated:

    [  P        Gᵀ  ] [dz]   [ −dP·z − dc ]
    [ −L(λ)G   L(s) ] [dλ] = [  −L(λ) dh  ]

where L(x) is the arrow matrix of x (x ∘ y = L(x) y).  At a strictly complementary solution this matrix is
nonsingular although L(s) and L(λ) are singular on the cone boundary, so it gives the exact derivative of the
solution map (a sliding contact's direction turning with the data included).  For an incoming gradient
ḡ = ∂L/∂z the adjoint system Kᵀ[u; v] = [ḡ; 0] gives

    ∂L/∂c = −u,   ∂L/∂P = −½(u zᵀ + z uᵀ),   ∂L/∂h = −L(λ) v   (h = −l on the rays: ∂L/∂l = λ_l·v_l).

No backpropagation through the iterations.
"""

from __future__ import annotations

import numpy as np
import torch

from diffcontact.solver import exact
from diffcontact.solver.ipm import IPMResult


class ImplicitConeQP(torch.autograd.Function):
    """Returns ``z_star`` (computed beforehand, without autograd) and differentiates it implicitly."""

    @staticmethod
    def forward(P, c, lower, z_star, result: IPMResult):  # noqa: D102
        return z_star.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):  # noqa: D102
        ctx.result = inputs[4]
        ctx.save_for_backward(output)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_z):  # noqa: D102
        (z,) = ctx.saved_tensors
        res: IPMResult = ctx.result
        B, n = z.shape
        u, v_l = adjoint_solve(res, grad_z)
        grad_P = grad_c = grad_l = None
        if ctx.needs_input_grad[0]:
            grad_P = -0.5 * (u.unsqueeze(-1) * z.unsqueeze(-2) + z.unsqueeze(-1) * u.unsqueeze(-2))
        if ctx.needs_input_grad[1]:
            grad_c = -u
        if ctx.needs_input_grad[2]:
            grad_l = res.on_l * res.lam_l * v_l
        return grad_P, grad_c, grad_l, None, None


def adjoint_solve(res: IPMResult, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve Kᵀ[u; v] = [g; 0] (module docstring); returns u: (B, n) and the rays' v: (B, K).

    Solved per element in the compiled kernel; where K is singular (a degenerate solution: a contact exactly
    at a stick/slip or touch/separate switch) the dense system is solved by least squares instead.
    """
    arrays = [
        np.ascontiguousarray(t.numpy())
        for t in (res.P, res.s_l, res.lam_l, res.s_q, res.lam_q, res.on, res.on_l, g.detach().to(torch.float64))
    ]
    d = res.s_q.shape[-1]
    u, v_l, ok = exact.adjoint_batch(*arrays[:7], d, arrays[7])
    u, v_l, ok = torch.from_numpy(u), torch.from_numpy(v_l), torch.from_numpy(ok)
    if not ok.all():
        u_ls, v_ls = _adjoint_lstsq(res, g, ~ok)
        u[~ok], v_l[~ok] = u_ls, v_ls
    return u, v_l


def _adjoint_lstsq(res: IPMResult, g: torch.Tensor, sel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares adjoint for the selected (degenerate) elements, weakly active cones taken as inactive."""
    d = res.s_q.shape[-1]
    n, K = g.shape[-1], res.on.shape[-1]
    parts = [
        np.ascontiguousarray(t[sel].numpy()) for t in (res.P, res.s_l, res.lam_l, res.s_q, res.lam_q, res.on, res.on_l)
    ]
    Kmat = torch.from_numpy(exact.kkt_matrix_batch(*parts, d, True))
    rhs = torch.zeros(Kmat.shape[0], Kmat.shape[-1], dtype=Kmat.dtype)
    rhs[:, :n] = g[sel]
    sol = torch.linalg.lstsq(Kmat.mT, rhs.unsqueeze(-1)).solution.squeeze(-1)
    return sol[:, :n], sol[:, n : n + K]
