"""Small dense SPD linear algebra vectorised over the batch.

torch's batched LAPACK calls pay a fixed cost per matrix (several µs), which dominates for the many tiny
(n ≤ 60) systems of contact problems.  These routines loop over the n columns instead and do every batch
element at once, so their cost grows with n, not with B.
"""

from __future__ import annotations

import torch


def cholesky_inverse_factor(H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """R = L⁻¹ for the Cholesky factor L of H, so that H⁻¹ = RᵀR.  H: (B, n, n) SPD.

    Returns (R, bad) with bad: (B,) True where H is not numerically positive definite (a pivot ≤ tiny); those
    elements get a unit pivot so that the others are unaffected.
    """
    B, n, _ = H.shape
    L = torch.zeros_like(H)
    bad = torch.zeros(B, dtype=torch.bool, device=H.device)
    for j in range(n):
        v = H[:, j:, j]
        if j:
            v = v - (L[:, j:, :j] @ L[:, j, :j].unsqueeze(-1)).squeeze(-1)
        piv = v[:, 0]
        small = ~(piv > 0)  # also catches NaN
        bad = bad | small
        d = torch.where(small, torch.ones_like(piv), piv).sqrt()
        L[:, j:, j] = v / d[:, None]
    # invert the lower-triangular L column by column: R L = I
    R = torch.zeros_like(H)
    diag = L.diagonal(dim1=-2, dim2=-1)
    for i in range(n):
        # row i of R: R[i, :i] = −(R[i, i]) · Σ_k L[i, k] R[k, :i] … done via forward substitution on rows
        R[:, i, i] = 1.0 / diag[:, i]
        if i:
            R[:, i, :i] = -(L[:, i, :i].unsqueeze(-2) @ R[:, :i, :i]).squeeze(-2) / diag[:, i : i + 1]
    return R, bad


def spd_solve(R: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """H⁻¹ b = Rᵀ(R b) with R from :func:`cholesky_inverse_factor`.  R: (B, n, n); b: (B, n)."""
    return (R.mT @ (R @ b.unsqueeze(-1))).squeeze(-1)


class SPDFactor:
    """A factorisation of a batch of SPD matrices H: (B, n, n) with ``solve(b)`` for b: (B, n).

    Small systems (n ≤ ``SMALL``) use the column-looped factor above, larger ones LAPACK's batched Cholesky.
    Elements that are not numerically positive definite get a small diagonal shift and are flagged in ``bad``
    if even that fails.
    """

    SMALL = 24

    def __init__(self, H: torch.Tensor):
        self.small = H.shape[-1] <= self.SMALL
        if self.small:
            R, bad = cholesky_inverse_factor(H)
            if bad.any():
                scale = H.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1.0)
                eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
                R2, bad2 = cholesky_inverse_factor(H + (1e-13 * scale * bad)[:, None, None] * eye)
                R = torch.where(bad[:, None, None], R2, R)
                bad = bad & bad2
            self.R, self.bad = R, bad
            return
        L, info = torch.linalg.cholesky_ex(H)
        bad = info != 0
        if bad.any():
            scale = H.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1.0)
            eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
            L2, info2 = torch.linalg.cholesky_ex(H + (1e-13 * scale * bad)[:, None, None] * eye)
            L = torch.where(bad[:, None, None], L2, L)
            bad = info2 != 0
        self.L, self.bad = L, bad

    def solve(self, b: torch.Tensor) -> torch.Tensor:
        """H⁻¹ b.  b: (B, n)."""
        if self.small:
            return spd_solve(self.R, b)
        return torch.cholesky_solve(b.unsqueeze(-1), self.L).squeeze(-1)
