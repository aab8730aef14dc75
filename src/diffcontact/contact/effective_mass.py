"""Inverse inertia with equality constraints, M̂⁻¹ = M⁻¹ − M⁻¹J_Eᵀ(J_E M⁻¹ J_Eᵀ)⁻¹J_E M⁻¹ (paper Eq. 8),
and the contact-space inverse inertia A = J_C M̂⁻¹ J_Cᵀ (Eq. 9), by Cholesky solves only.
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.constraints import Constraints
from diffcontact.dynamics.inertia import apply_blocks


def constrained_inverse_inertia_times(
    Minv: torch.Tensor, constraints: Constraints, x: torch.Tensor, Jc: torch.Tensor
) -> torch.Tensor:
    """M̂⁻¹ J_Cᵀ: (B, D, C) for M⁻¹ blocks (n, q, q), positions x (B, P, d) and J_C (B, C, D).

    Never forms an inverse or an eigendecomposition: G = J_E M⁻¹ J_Eᵀ is factored by Cholesky.
    """
    B, P, d = x.shape
    W = apply_blocks(Minv, Jc.mT.reshape(B, P, d, -1)).reshape(B, P * d, -1)  # M⁻¹J_Cᵀ
    if constraints.count == 0:
        return W
    JE = constraints.jac(x)
    MinvJEt = apply_blocks(Minv, JE.mT.reshape(B, P, d, -1)).reshape(B, P * d, -1)
    L, info = torch.linalg.cholesky_ex(JE @ MinvJEt)
    if bool((info != 0).any()):
        raise FloatingPointError("effective mass: J_E M⁻¹ J_Eᵀ is not positive definite (degenerate constraints)")
    return W - MinvJEt @ torch.cholesky_solve(JE @ W, L)


def contact_inverse_inertia(Jc: torch.Tensor, MhatinvJt: torch.Tensor) -> torch.Tensor:
    """A = J_C M̂⁻¹ J_Cᵀ (B, C, C), symmetrised (PSD; singular with more rows than free DOF)."""
    A = Jc @ MhatinvJt
    return 0.5 * (A + A.mT)
