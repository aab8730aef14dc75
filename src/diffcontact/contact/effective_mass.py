"""Inverse inertia with equality constraints, M̂⁻¹ = M⁻¹ − M⁻¹J_Eᵀ(J_E M⁻¹ J_Eᵀ)⁻¹J_E M⁻¹ (paper Eq. 8),
and the contact-space inverse inertia A = J_C M̂⁻¹ J_Cᵀ (Eq. 9), in a factored form that is PSD by construction.

With M⁻¹ = L Lᵀ (closed form per body, ``inverse_factor_blocks``) and Q an orthonormal basis of the range of
Lᵀ J_Eᵀ (QR), M̂⁻¹ = L (I − QQᵀ) Lᵀ, so A = Z Zᵀ with Z = J_C L (I − QQᵀ).  Formed as the difference of Eq. 8,
A loses what the cancellation loses: with learned moments far from the masses (e^±8 m² per unit mass) float32 left
it indefinite at 0.4 % of its scale; as Z Zᵀ it is PSD up to the rounding of one product.
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.constraints import Constraints
from diffcontact.dynamics.inertia import apply_blocks


def effective_inverse_inertia(
    L: torch.Tensor, constraints: Constraints, x: torch.Tensor, Jc: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(M̂⁻¹J_Cᵀ (B, D, C), A = J_C M̂⁻¹ J_Cᵀ (B, C, C)) for M⁻¹ factor blocks L (n, q, q) (L Lᵀ = M⁻¹ blocks),
    positions x (B, P, d) in m and contact Jacobian J_C (B, C, D).

    Raises FloatingPointError where the equality constraints are degenerate (J_E not of full row rank).
    """
    B, P, d = x.shape
    Lt = L.mT

    def times(blocks, y):  # blocks applied per body to the columns of y (B, D, k)
        return apply_blocks(blocks, y.reshape(B, P, d, -1)).reshape(B, P * d, -1)

    Zt = times(Lt, Jc.mT)  # Lᵀ J_Cᵀ
    if constraints.count:
        Q, R = torch.linalg.qr(times(Lt, constraints.jac(x).mT))
        diag = R.diagonal(dim1=-2, dim2=-1).abs()
        if bool((diag <= torch.finfo(diag.dtype).eps * diag.shape[-1] * diag.amax(-1, keepdim=True)).any()):
            raise FloatingPointError("effective mass: the equality constraints are degenerate (J_E is rank-deficient)")
        Zt = Zt - Q @ (Q.mT @ Zt)
    return times(L, Zt), Zt.mT @ Zt
