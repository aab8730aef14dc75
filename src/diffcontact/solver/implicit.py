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

import torch

from diffcontact.solver.ipm import IPMResult


class ImplicitConeQP(torch.autograd.Function):
    """Returns ``z_star`` (computed beforehand, without autograd) and differentiates it implicitly."""

    @staticmethod
    def forward(P, c, lower, z_star, result: IPMResult, d: int):  # noqa: D102
        return z_star.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):  # noqa: D102
        _, _, _, _, result, d = inputs
        ctx.result = result
        ctx.d = d
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
        return grad_P, grad_c, grad_l, None, None, None


def _arrow(x: torch.Tensor) -> torch.Tensor:
    """Arrow matrix L(x) = [[x0, x1ᵀ], [x1, x0·I]]: (..., d) -> (..., d, d)."""
    d = x.shape[-1]
    L = x[..., :1, None] * torch.eye(d, dtype=x.dtype)
    L[..., 0, 1:] = x[..., 1:]
    L[..., 1:, 0] = x[..., 1:]
    return L


def adjoint_solve(res: IPMResult, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve Kᵀ[u; v] = [g; 0] (module docstring); returns u: (B, n) and the rays' v: (B, K)."""
    B, K = res.on.shape
    d = res.s_q.shape[-1]
    n = K * d
    soc = d > 1
    m = K * (d + 1) if soc else K
    N = n + m
    dt = res.P.dtype
    on_l = res.on_l.to(dt)
    on_q = res.on.to(dt)
    Kmat = torch.zeros(B, N, N, dtype=dt)
    Kmat[:, :n, :n] = res.P
    k = torch.arange(K)
    row_n = k * d  # the normal variable of each contact
    ray = n + k  # the rays' multiplier rows/columns
    # Gᵀ: −1 at (normal of k, ray k); −I on the cone block of k
    Kmat[:, row_n, ray] = -on_l
    # −L(λ)G = +λ_l at (ray k, normal k); L(s) = s_l; unused rays: identity row (dλ = 0)
    Kmat[:, ray, row_n] = on_l * res.lam_l
    Kmat[:, ray, ray] = on_l * res.s_l + (1.0 - on_l)
    if soc:
        i = torch.arange(d)
        var = (k[:, None] * d + i[None, :]).reshape(-1)  # (K·d,)
        mult = n + K + var
        Kmat[:, var, mult] = -on_q.repeat_interleave(d, -1)
        blk = k[:, None, None] * d
        rows = (n + K + blk + i[None, :, None]).expand(K, d, d)
        cols_v = (blk + i[None, None, :]).expand(K, d, d)
        cols_m = (n + K + blk + i[None, None, :]).expand(K, d, d)
        Lam = _arrow(res.lam_q) * on_q[..., None, None]
        Sq = _arrow(res.s_q) * on_q[..., None, None] + (1.0 - on_q)[..., None, None] * torch.eye(d, dtype=dt)
        Kmat[:, rows, cols_v] = Lam
        Kmat[:, rows, cols_m] = Sq
    rhs = torch.zeros(B, N, dtype=dt)
    rhs[:, :n] = g
    sol, info = torch.linalg.solve_ex(Kmat.mT, rhs)
    bad = (info != 0) | ~torch.isfinite(sol).all(-1)
    if bad.any():  # singular (degenerate solution): least squares instead
        sol_ls = torch.linalg.lstsq(Kmat.mT[bad], rhs[bad].unsqueeze(-1)).solution.squeeze(-1)
        sol[bad] = sol_ls
    return sol[:, :n], sol[:, n : n + K]
