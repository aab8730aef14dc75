"""Constrained Hamiltonian dynamics in Cartesian coordinates (x, p) (paper Suppl. B; Finzi et al. 2020).

H(x, p) = ½ pᵀM⁻¹p + V(x); ż = P(J∇H) with J = [[0, I], [−I, 0]], Ψ = (Φ(x), J_E(x) M⁻¹ p) and the
projection P(Y) = Y − J DΨ (DΨᵀ J DΨ)⁻¹ DΨᵀ Y. ∇H comes from autograd, so a learned V fits unchanged.
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.constraints import Constraints
from diffcontact.dynamics.inertia import apply_blocks, body_blocks
from diffcontact.state import Params


def hamiltonian(params: Params, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """H = ½ pᵀM⁻¹p + V(x): x, p (B, P, d) -> (B,) in J."""
    _, Minv = body_blocks(params.inertia)
    return 0.5 * (p * apply_blocks(Minv, p)).flatten(1).sum(-1) + params.potential(x)


def hamiltonian_field(
    constraints: Constraints, params: Params, x: torch.Tensor, p: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The projected Hamiltonian vector field (ẋ, ṗ), each (B, P, d)."""
    B, P, d = x.shape
    outer = torch.is_grad_enabled()
    with torch.enable_grad():
        xg = x if x.requires_grad else x.detach().requires_grad_(True)
        pg = p if p.requires_grad else p.detach().requires_grad_(True)
        H = hamiltonian(params, xg, pg)
        dHdx, dHdp = torch.autograd.grad(H.sum(), (xg, pg), create_graph=outer, allow_unused=True)
    dHdx = torch.zeros_like(x) if dHdx is None else dHdx
    Y = torch.cat([dHdp.reshape(B, -1), -dHdx.reshape(B, -1)], dim=-1)  # J∇H, (B, 2D)
    if constraints.count == 0:
        return Y[:, : P * d].reshape(B, P, d), Y[:, P * d :].reshape(B, P, d)
    _, Minv = body_blocks(params.inertia)
    v = apply_blocks(Minv, p)
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
