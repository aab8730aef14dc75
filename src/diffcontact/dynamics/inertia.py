"""Inertia of point masses and extended bodies in Cartesian coordinates, in closed form per body.

An extended body in d dimensions is d + 1 points: its centre c and c + e_k for the unit body axes e_k.
With mass m and per-axis second moments per unit mass μ_k, its block (acting identically on each of the d
coordinates) is M = m [[1 + Σμ, −μᵀ], [−μ, diag μ]] and M⁻¹ = (1/m) (11ᵀ + diag(0, 1/μ)). A point mass is
the 1×1 block m. The full mass matrix is kron(blockdiag(blocks), I_d) in the (P, d) point layout.
"""

from __future__ import annotations

import torch

from diffcontact.state import Inertia


def body_blocks(inertia: Inertia) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, M⁻¹) blocks, each (n_bodies, k+1, k+1), from masses (n_bodies,) and moments (n_bodies, k)."""
    m, mom = inertia.masses, inertia.moments
    k = mom.shape[-1]
    if k == 0:
        return m[:, None, None], (1.0 / m)[:, None, None]
    top = torch.cat([(1.0 + mom.sum(-1, keepdim=True)), -mom], dim=-1)  # (n, k+1)
    low = torch.cat([-mom[..., None], torch.diag_embed(mom)], dim=-1)  # (n, k, k+1)
    M = m[:, None, None] * torch.cat([top[:, None, :], low], dim=-2)
    inv_diag = torch.cat([torch.zeros_like(mom[:, :1]), 1.0 / mom], dim=-1)
    ones = torch.ones(m.shape[0], k + 1, k + 1, dtype=m.dtype, device=m.device)
    Minv = (ones + torch.diag_embed(inv_diag)) / m[:, None, None]
    return M, Minv


def inverse_factor_blocks(inertia: Inertia) -> torch.Tensor:
    """Blocks L (n_bodies, k+1, k+1) with L Lᵀ = the M⁻¹ blocks of :func:`body_blocks`, in closed form:
    L = m^(−1/2) [1 | diag(0, μ^(−1/2))] (first column all ones), exact for any moments (no factorisation)."""
    m, mom = inertia.masses, inertia.moments
    k = mom.shape[-1]
    ones = torch.ones(m.shape[0], k + 1, 1, dtype=m.dtype, device=m.device)
    zero = torch.zeros(m.shape[0], 1, dtype=m.dtype, device=m.device)
    spread = torch.diag_embed(torch.cat([zero, mom.rsqrt()], dim=-1))[..., 1:]
    return torch.cat([ones, spread], dim=-1) * m.rsqrt()[:, None, None]


def apply_blocks(blocks: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Multiply points by the per-body blocks: blocks (n, k+1, k+1), y (B, P, d, ...) -> same shape as y.

    P = n (k+1) with the points of a body contiguous. Use with M or M⁻¹ blocks from :func:`body_blocks`.
    """
    n, q, _ = blocks.shape
    if q == 1:  # point masses: a scale per point (the same products as the einsum, without its copies)
        return y * blocks.to(y.dtype).reshape(1, n, *[1] * (y.dim() - 2))
    shaped = y.reshape(y.shape[0], n, q, *y.shape[2:])
    out = torch.einsum("nij,bnj...->bni...", blocks.to(y.dtype), shaped)
    return out.reshape(y.shape)


def dense(blocks: torch.Tensor, d: int) -> torch.Tensor:
    """The full (D, D) matrix kron(blockdiag(blocks), I_d), D = P d, in the flattened (P, d) layout."""
    return torch.kron(torch.block_diag(*blocks.unbind(0)), torch.eye(d, dtype=blocks.dtype, device=blocks.device))


def kinetic_energy(inertia: Inertia, v: torch.Tensor) -> torch.Tensor:
    """½ vᵀ M v: v (B, P, d) -> (B,)."""
    M, _ = body_blocks(inertia)
    return 0.5 * (v * apply_blocks(M, v)).flatten(1).sum(-1)
