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

The chain rule through the substitution f = γ·T⊙z (P = T A T, c = T q/γ, T = S·D(μ)) is applied in closed
form: ∂L/∂A = −½(T u (T z)ᵀ + T z (T u)ᵀ) and matrix–vector products for ∂L/∂T.  No backpropagation through the
iterations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from diffcontact.solver import exact, lanes, scaling
from diffcontact.solver.exact import contact_dims
from diffcontact.solver.ipm import IPMResult


@dataclass
class ScaledSolution:
    """A solved batch and its substitution f = γ·T⊙z, T = S·D (see ``problem.py``); everything the backward
    pass needs, float64, without autograd.  Shapes: B batch, K contacts, n = K·d."""

    A: torch.Tensor  # (B, n, n) the symmetrised A
    q: torch.Tensor  # (B, n)
    T: torch.Tensor  # (B, n) S·D on active rows, 0 elsewhere
    S: torch.Tensor  # (B, n) S on active rows (∂T/∂μ on the tangential rows)
    gamma: torch.Tensor  # (B,)
    lower_scale: torch.Tensor  # (B, K) ∂l̂/∂lower: 1/(σγ) on active contacts with a non-negligible bound, else 0
    slide: torch.Tensor  # (B, K) −∂c_n/∂μ of frictionless sliding contacts (σ‖g_t‖/γ), else 0
    z: torch.Tensor  # (B, n) solution in z
    result: IPMResult


class ImplicitConeQP(torch.autograd.Function):
    """f(A, q, mu, lower) of a batch solved beforehand (``ScaledSolution``), differentiated implicitly.

    The backward pass solves the adjoint system once per element and applies the chain rule of the scaling
    in closed form (matrix–vector products, no (B, n, n) intermediate besides ∂L/∂A itself).
    """

    @staticmethod
    def forward(ctx, A, q, mu, lower, sol: ScaledSolution):  # noqa: D102
        # (the form with ctx: the one with setup_context binds the arguments by signature on every call, ≈ 20 µs)
        ctx.sol = sol
        ctx.dtypes = (A.dtype, q.dtype, mu.dtype, lower.dtype)
        return (sol.gamma[:, None] * sol.T * sol.z).to(A.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_f):  # noqa: D102
        sol: ScaledSolution = ctx.sol
        res = sol.result
        d = sol.z.shape[-1] // res.on.shape[-1]
        gf = grad_f.to(torch.float64)
        u, v_l = adjoint_solve(res, sol.gamma[:, None] * sol.T * gf)
        need = np.array(ctx.needs_input_grad[:4], dtype=np.bool_)
        arrays = [
            np.ascontiguousarray(t.numpy())
            for t in (u, v_l, sol.z, gf, sol.A, sol.q, sol.T, sol.S, sol.gamma, res.lam_l, res.on_l, sol.lower_scale)
        ] + [np.ascontiguousarray(sol.slide.numpy())]
        grads = scaling.chain_rule_batch(*arrays, contact_dims(d), need)
        grads = [torch.from_numpy(g) if want else None for g, want in zip(grads, need)]
        return tuple(g.to(dt) if g is not None else None for g, dt in zip(grads, ctx.dtypes)) + (None,)


def adjoint_solve(res: IPMResult, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve Kᵀ[u; v] = [g; 0] (module docstring); returns u: (B, n) and the rays' v: (B, K).

    Solved in the compiled kernel (``lanes.py``); where K is singular (a degenerate solution: a contact exactly
    at a stick/slip or touch/separate switch) the dense system is solved by least squares instead.
    """
    arrays = [
        np.ascontiguousarray(t.numpy())
        for t in (res.P, res.s_l, res.lam_l, res.s_q, res.lam_q, res.on, res.on_l, g.detach().to(torch.float64))
    ]
    u, v_l, ok = lanes.adjoint(*arrays[:7], res.s_q.shape[-1], arrays[7])
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
    Kmat = torch.from_numpy(exact.kkt_matrix_batch(*parts, contact_dims(d), True))
    rhs = torch.zeros(Kmat.shape[0], Kmat.shape[-1], dtype=Kmat.dtype)
    rhs[:, :n] = g[sel]
    sol = torch.linalg.lstsq(Kmat.mT, rhs.unsqueeze(-1)).solution.squeeze(-1)
    return sol[:, :n], sol[:, n : n + K]
