"""Algebra of the two cones of a contact: the non-negative ray and the second-order (Lorentz) cone.

Second-order cone vectors have shape (..., d) with x[..., 0] the scalar part: x ∈ Q ⟺ x0 ≥ ‖x[1:]‖.
Everything here is batched, float64, and free of Python loops.
"""

from __future__ import annotations

import torch


def soc_det(x: torch.Tensor) -> torch.Tensor:
    """x0² − ‖x1‖², computed as a product for accuracy near the boundary.  x: (..., d) -> (...)."""
    r = x[..., 1:].norm(dim=-1)
    return (x[..., 0] - r) * (x[..., 0] + r)


def soc_min_eig(x: torch.Tensor) -> torch.Tensor:
    """Smallest Jordan eigenvalue x0 − ‖x1‖ (positive inside the cone).  x: (..., d) -> (...)."""
    return x[..., 0] - x[..., 1:].norm(dim=-1)


def soc_identity(shape: tuple[int, ...], d: int, like: torch.Tensor) -> torch.Tensor:
    """The cone's identity e = (1, 0, …, 0) broadcast to (*shape, d)."""
    e = torch.zeros(*shape, d, dtype=like.dtype, device=like.device)
    e[..., 0] = 1.0
    return e


def soc_prod(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Jordan product x ∘ y = (xᵀy, x0·y1 + y0·x1).  x, y: (..., d)."""
    head = (x * y).sum(-1, keepdim=True)
    tail = x[..., :1] * y[..., 1:] + y[..., :1] * x[..., 1:]
    return torch.cat([head, tail], dim=-1)


def soc_div(x: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """The u with x ∘ u = r, for x inside the cone.  x, r: (..., d)."""
    x0, x1 = x[..., :1], x[..., 1:]
    u0 = (x0 * r[..., :1] - (x1 * r[..., 1:]).sum(-1, keepdim=True)) / soc_det(x).unsqueeze(-1)
    u1 = (r[..., 1:] - u0 * x1) / x0
    return torch.cat([u0, u1], dim=-1)


def soc_max_step(x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
    """Largest α ≥ 0 with x + α·dx in the cone, for x inside it (inf if unbounded).  (..., d) -> (...).

    Smallest positive root of (x0 + α dx0)² − ‖x1 + α dx1‖² = c + 2bα + aα² (c > 0).
    """
    a = soc_det(dx)
    b = x[..., 0] * dx[..., 0] - (x[..., 1:] * dx[..., 1:]).sum(-1)
    c = soc_det(x).clamp_min(0.0)
    disc_raw = b * b - a * c
    # a discriminant that is negative only by rounding is a double root (the ray touches the boundary)
    has_real = disc_raw >= -1e-12 * (b * b + (a * c).abs())
    sq = disc_raw.clamp_min(0.0).sqrt()
    inf = torch.full_like(a, float("inf"))
    # Stable roots: t1 = −(b + sign(b)·√disc)/a and t2 = c/(−(b + sign(b)·√disc)).
    qq = -(b + torch.where(b >= 0, sq, -sq))
    r1 = torch.where(a != 0, qq / torch.where(a != 0, a, torch.ones_like(a)), inf)
    r2 = torch.where(qq != 0, c / torch.where(qq != 0, qq, torch.ones_like(qq)), inf)
    r1 = torch.where(has_real & (r1 > 0), r1, inf)
    r2 = torch.where(has_real & (r2 > 0), r2, inf)
    alpha = torch.minimum(r1, r2)
    # With no positive root the ray never leaves the cone (an exit crosses the boundary, a root).
    return alpha


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
