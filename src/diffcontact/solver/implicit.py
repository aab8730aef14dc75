"""Implicit differentiation of the standard-form cone QP at its solution (one autograd Function).

At the solution the optimality conditions, linearised with the final Nesterov–Todd scaling W, read

    [ P   Gᵀ  ] [dz]   [ −dP·z − dc ]
    [ G  −W²  ] [dλ] = [     dh     ]

The matrix is symmetric, so for an incoming gradient ḡ = ∂L/∂z the adjoint solve is H u = ḡ with the same
H = P + GᵀW⁻²G as the forward's last factorisation, and v = W⁻²G u.  Then

    ∂L/∂c = −u,   ∂L/∂P = −½(u zᵀ + z uᵀ),   ∂L/∂h = v   (h = −l on the rays, so ∂L/∂l = (λ/s)·u_n).

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
        d = ctx.d
        B, n = z.shape
        u = res.factor.solve(grad_z)
        grad_P = grad_c = grad_l = None
        if ctx.needs_input_grad[0]:
            grad_P = -0.5 * (u.unsqueeze(-1) * z.unsqueeze(-2) + z.unsqueeze(-1) * u.unsqueeze(-2))
        if ctx.needs_input_grad[1]:
            grad_c = -u
        if ctx.needs_input_grad[2]:
            grad_l = res.w2_lin * u.view(B, n // d, d)[..., 0]
        return grad_P, grad_c, grad_l, None, None, None
