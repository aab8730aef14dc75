"""Contact frames (normal first, then tangents) and the weights of a contact point over a body's points."""

from __future__ import annotations

import torch


def tangent_frame(n: torch.Tensor, dc: int) -> torch.Tensor:
    """Orthonormal contact frame with the unit normal first: n (..., d) -> (..., dc, d).

    dc = 1 gives the normal only; in 2D the tangent is n rotated by +90°; in 3D the tangents complete n to a
    right-handed basis using the coordinate axis least aligned with n.
    """
    if dc == 1:
        return n[..., None, :]
    d = n.shape[-1]
    if d == 2:
        return torch.stack([n, torch.stack([-n[..., 1], n[..., 0]], -1)], dim=-2)
    axis = torch.zeros_like(n)
    pick = n.abs().argmin(dim=-1, keepdim=True)
    axis = axis.scatter(-1, pick, 1.0)
    t1 = axis - (axis * n).sum(-1, keepdim=True) * n
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(n, t1)
    return torch.stack([n, t1, t2], dim=-2)


def point_weights(x: torch.Tensor, pts: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """Weights c̃ (B, K, q) of the world point centre + offset over a body's q points.

    x: (B, P_ext, d) positions; pts: (K, q) point indices of the body (centre first, then centre + e_k);
    offset: (B, K, d) in m. With orthonormal axes e_k, c̃ = [1 − Σ c_k, c_k] and c_k = offset · e_k, so the
    contact point's velocity is Σ_p c̃_p v_p. A point mass (q = 1) has c̃ = [1].
    """
    q = pts.shape[1]
    if q == 1:
        return offset.new_ones(offset.shape[0], pts.shape[0], 1)
    centre = x[:, pts[:, 0]]
    axes = x[:, pts[:, 1:]] - centre[:, :, None]  # (B, K, q-1, d)
    c = (axes * offset[:, :, None]).sum(-1)
    return torch.cat([1.0 - c.sum(-1, keepdim=True), c], dim=-1)
