"""Batched algebra of the second-order (Lorentz) cone used by the backward pass.

Vectors have shape (..., d) with x[..., 0] the scalar part: x ∈ Q ⟺ x0 ≥ ‖x[1:]‖.
"""

from __future__ import annotations

import torch


def soc_det(x: torch.Tensor) -> torch.Tensor:
    """x0² − ‖x1‖², computed as a product for accuracy near the boundary.  x: (..., d) -> (...)."""
    r = x[..., 1:].norm(dim=-1)
    return (x[..., 0] - r) * (x[..., 0] + r)


class SocNTScaling:
    """Nesterov–Todd scaling W of one second-order cone per (batch, contact): W λ = W⁻¹ s (= λ̃).

    W = η(2 vvᵀ − J), W⁻¹ = (1/η)(2 Jv (Jv)ᵀ − J), with J = diag(1, −1, …, −1) and v the square root of
    the normalised NT scaling point w̄ (Vandenberghe, "The CVXOPT linear and quadratic cone program solvers").
    s, lam: (..., d) strictly inside the cone.
    """

    def __init__(self, s: torch.Tensor, lam: torch.Tensor):
        s_nrm = soc_det(s).clamp_min(1e-300).sqrt()
        l_nrm = soc_det(lam).clamp_min(1e-300).sqrt()
        s_bar = s / s_nrm.unsqueeze(-1)
        l_bar = lam / l_nrm.unsqueeze(-1)
        gamma = ((1.0 + (s_bar * l_bar).sum(-1)) / 2.0).clamp_min(1e-300).sqrt()
        jl_bar = l_bar.clone()
        jl_bar[..., 1:] = -jl_bar[..., 1:]
        w_bar = (s_bar + jl_bar) / (2.0 * gamma.unsqueeze(-1))  # NT scaling point, normalised
        # W uses its Jordan square root v = (w̄ + e)/√(2(w̄0 + 1)) (so that W² = P(w̄)).
        w_bar[..., 0] += 1.0
        self.w = w_bar / (2.0 * w_bar[..., :1]).sqrt()
        self.jw = self.w.clone()
        self.jw[..., 1:] = -self.jw[..., 1:]
        self.eta = (s_nrm / l_nrm).sqrt()

    def matrices(self) -> tuple[torch.Tensor, torch.Tensor]:
        """W and W⁻¹ as matrices: (..., d, d) each."""
        d = self.w.shape[-1]
        J = torch.ones(d, dtype=self.w.dtype, device=self.w.device)
        J[1:] = -1.0
        J = torch.diag(J)
        eta = self.eta[..., None, None]
        w = eta * (2.0 * self.w.unsqueeze(-1) * self.w.unsqueeze(-2) - J)
        w_inv = (2.0 * self.jw.unsqueeze(-1) * self.jw.unsqueeze(-2) - J) / eta
        return w, w_inv
