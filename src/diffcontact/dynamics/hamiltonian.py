"""Constrained Hamiltonian dynamics in Cartesian coordinates (x, p) (paper Suppl. B; Finzi et al. 2020).

H(x, p) = ½ pᵀM⁻¹p + V(x); ż = P(J∇H) with J = [[0, I], [−I, 0]], Ψ = (Φ(x), J_E(x) M⁻¹ p) and the
projection P(Y) = Y − J DΨ (DΨᵀ J DΨ)⁻¹ DΨᵀ Y. ∂H/∂p = M⁻¹p in closed form and ∂H/∂x = ∇V by autograd, so a
learned V fits unchanged.
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.constraints import Constraints
from diffcontact.dynamics.inertia import apply_blocks, body_blocks
from diffcontact.dynamics.lagrangian import potential_force
from diffcontact.state import Params


def hamiltonian_field(
    constraints: Constraints, params: Params, x: torch.Tensor, p: torch.Tensor, Minv: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The projected Hamiltonian vector field (ẋ, ṗ), each (B, P, d); Minv: the M⁻¹ blocks if already computed."""
    B, P, d = x.shape
    # ∂H/∂p = M⁻¹p and ∂H/∂x = ∇V(x) taken separately: an autograd gradient of H itself with respect to the
    # state would be the total derivative, which after a contact step (p depends on x through the impulse) is not
    # the partial one the field needs.
    if Minv is None:
        _, Minv = body_blocks(params.inertia)
    dHdp = apply_blocks(Minv, p)
    dHdx = -potential_force(params, x)
    Y = torch.cat([dHdp.reshape(B, -1), -dHdx.reshape(B, -1)], dim=-1)  # J∇H, (B, 2D)
    if constraints.count == 0:
        return Y[:, : P * d].reshape(B, P, d), Y[:, P * d :].reshape(B, P, d)
    v = dHdp
    JE = constraints.jac(x)  # (B, E, D)
    dPhidot_dx = constraints.jac_dot(x, v)  # ∂(J_E M⁻¹p)/∂x
    MinvJt = apply_blocks(Minv, JE.mT.reshape(B, P, d, -1)).reshape(B, P * d, -1)
    zeros = torch.zeros_like(JE.mT)
    DPsi = torch.cat([torch.cat([JE.mT, dPhidot_dx.mT], -1), torch.cat([zeros, MinvJt], -1)], dim=-2)
    JDPsi = torch.cat([DPsi[:, P * d :], -DPsi[:, : P * d]], dim=-2)  # J DΨ, (B, 2D, 2E)
    S = DPsi.mT @ JDPsi  # (B, 2E, 2E), antisymmetric, invertible for independent constraints
    corr = JDPsi @ torch.linalg.solve(S, DPsi.mT @ Y[..., None])
    Z = Y - corr[..., 0]
    return Z[:, : P * d].reshape(B, P, d), Z[:, P * d :].reshape(B, P, d)


def momentum(params: Params, v: torch.Tensor) -> torch.Tensor:
    """p = M v: (B, P, d) -> (B, P, d)."""
    M, _ = body_blocks(params.inertia)
    return apply_blocks(M, v)


def velocity(params: Params, p: torch.Tensor) -> torch.Tensor:
    """v = M⁻¹ p: (B, P, d) -> (B, P, d)."""
    _, Minv = body_blocks(params.inertia)
    return apply_blocks(Minv, p)
