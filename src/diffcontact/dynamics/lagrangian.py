"""Constrained Lagrangian dynamics in Cartesian coordinates (x, v) (paper Suppl. B).

v̇ = M⁻¹f − M⁻¹J_Eᵀλ with f = −∇V(x) and λ = (J_E M⁻¹ J_Eᵀ)⁻¹ (J_E M⁻¹ f + J̇_E v), so that the
accelerations keep J_E v = 0. ∇V comes from autograd, so a learned potential runs through the same code.
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.constraints import Constraints
from diffcontact.dynamics.inertia import apply_blocks, body_blocks
from diffcontact.dynamics.potentials import gradient_force
from diffcontact.state import ForcePotential, Params


def potential_force(params: Params, x: torch.Tensor) -> torch.Tensor:
    """f = −∇V(x) of ``params.potential_energy``: x (B, P, d) -> (B, P, d) in N; the potential's own closed form
    (:class:`~diffcontact.state.ForcePotential`: the known potentials and the learned networks), else by autograd.

    The graph of ∇V is kept when gradients are enabled outside (training, gradient tests), so the force is
    differentiable w.r.t. x and the potential's parameters; under ``torch.no_grad`` it is not.
    """
    if isinstance(params.potential, ForcePotential):
        return params.potential.force(x, params.inertia)
    return gradient_force(params.potential, x, params.inertia)


def constrained_acceleration(
    constraints: Constraints, Minv: torch.Tensor, x: torch.Tensor, v: torch.Tensor, force: torch.Tensor
) -> torch.Tensor:
    """a = M⁻¹f − M⁻¹J_Eᵀλ (B, P, d) for force (B, P, d) and M⁻¹ blocks (n, q, q); Cholesky solve in λ."""
    a0 = apply_blocks(Minv, force)
    if constraints.count == 0:
        return a0
    B, P, d = x.shape
    J = constraints.jac(x)  # (B, E, D)
    Jdot = constraints.jac_dot(x, v)
    MinvJt = apply_blocks(Minv, J.mT.reshape(B, P, d, -1)).reshape(B, P * d, -1)
    G = J @ MinvJt
    rhs = J @ a0.reshape(B, -1, 1) + Jdot @ v.reshape(B, -1, 1)
    L, info = torch.linalg.cholesky_ex(G)
    if bool((info != 0).any()):
        bad = ~(torch.isfinite(x).flatten(1).all(1) & torch.isfinite(v).flatten(1).all(1))
        if bool(bad.any()):  # (a NaN state makes G NaN: say so, not that the constraints are degenerate)
            raise FloatingPointError(
                f"constrained dynamics: non-finite position or velocity in {int(bad.sum())} batch elements "
                f"(first: {int(bad.nonzero()[0])})"
            )
        raise FloatingPointError(
            "constrained dynamics: J_E M⁻¹ J_Eᵀ is not positive definite "
            f"in {int((info != 0).sum())} batch elements (degenerate constraints)"
        )
    lam = torch.cholesky_solve(rhs, L)
    return a0 - (MinvJt @ lam).reshape(B, P, d)


def lagrangian_field(
    constraints: Constraints, params: Params, x: torch.Tensor, v: torch.Tensor, Minv: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The vector field (ẋ, v̇) = (v, a(x, v)) of the constrained Lagrangian system, each (B, P, d).

    Minv: the M⁻¹ blocks of ``params.inertia`` (:func:`body_blocks`) if already computed (once per RK4 step)."""
    if Minv is None:
        _, Minv = body_blocks(params.inertia)
    return v, constrained_acceleration(constraints, Minv, x, v, potential_force(params, x))
