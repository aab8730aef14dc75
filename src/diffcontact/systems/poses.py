"""Rigid-body poses and the 4-point state of a 3-D extended body, both ways.

A body's state in this package is its centre c and the three axis points c + R e_k (k = 1, 2, 3) with their
velocities (systems/common.rigid_body_distances keeps the axes orthonormal). A pose is the centre and a unit
quaternion (w, x, y, z; Hamilton convention, body to world), a twist is the centre's velocity (world frame) and
the angular velocity ω in the body frame, so that Ṙ = R [ω]×.
"""

from __future__ import annotations

import numpy as np
import torch


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of unit quaternions q (..., 4), w first (normalised here)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, -1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (..., 4), w first and w ≥ 0, of rotation matrices R (..., 3, 3).

    Of the four algebraically equal forms, each element takes the one with the largest denominator (Shepperd's
    choice), so the result is accurate to rounding for every rotation."""
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack(
                [1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
            ),
            torch.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + 2 * m[..., 0, 0] - tr,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 + 2 * m[..., 1, 1] - tr,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 + 2 * m[..., 2, 2] - tr,
                ],
                -1,
            ),
        ],
        -2,
    )  # (..., 4, 4): row i is 4 q_i q (each proportional to q)
    pick = torch.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1).argmax(-1)
    q = torch.gather(cands, -2, pick[..., None, None].expand(*pick.shape, 1, 4))[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)  # fmt: skip


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew matrices [w]× (..., 3, 3) of vectors w (..., 3)."""
    z = torch.zeros_like(w[..., 0])
    rows = (z, -w[..., 2], w[..., 1], w[..., 2], z, -w[..., 0], -w[..., 1], w[..., 0], z)
    return torch.stack(rows, -1).reshape(*w.shape[:-1], 3, 3)


def pose_to_points(
    position: torch.Tensor, quaternion: torch.Tensor, velocity: torch.Tensor, omega_body: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The 4-point state (x, v) (..., 4, 3) of poses and twists: position, velocity (..., 3) in m and m/s (world),
    quaternion (..., 4) w first, omega_body (..., 3) in rad/s (body frame)."""
    R = quaternion_to_matrix(quaternion)
    Rdot = R @ hat(omega_body)
    x = torch.cat([position[..., None, :], position[..., None, :] + R.mT], dim=-2)
    v = torch.cat([velocity[..., None, :], velocity[..., None, :] + Rdot.mT], dim=-2)
    return x, v


def nearest_rotation(M: torch.Tensor) -> torch.Tensor:
    """The rotation nearest to M (..., 3, 3) in the Frobenius norm (its polar factor, det +1)."""
    U, _, Vh = torch.linalg.svd(M)
    D = torch.ones_like(M[..., 0])
    D[..., 2] = torch.linalg.det(U @ Vh).sign()
    return U @ torch.diag_embed(D) @ Vh


def points_to_pose(x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Poses and twists of 4-point states x, v (..., 4, 3): (position (..., 3) m, quaternion (..., 4) w first,
    velocity (..., 3) m/s, omega_body (..., 3) rad/s).

    The axes are taken to their nearest rotation (they drift from orthonormal only by the integrator's constraint
    error); ω is the axial part of Rᵀ Ṙ (least squares where Ṙ is not exactly tangent)."""
    centre, dc = x[..., 0, :], v[..., 0, :]
    R = nearest_rotation((x[..., 1:, :] - centre[..., None, :]).mT)
    Rdot = (v[..., 1:, :] - dc[..., None, :]).mT
    W = R.mT @ Rdot
    omega = 0.5 * torch.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1
    )
    return centre, matrix_to_quaternion(R), dc, omega


def rotation_vector(q: torch.Tensor) -> torch.Tensor:
    """Rotation vectors (..., 3) (axis × angle in [0, π], rad) of unit quaternions q (..., 4), w first."""
    q = torch.where(q[..., :1] < 0, -q, q)
    w, u = q[..., 0], q[..., 1:]
    s = u.norm(dim=-1)
    angle = 2.0 * torch.atan2(s, w)
    # angle / s, with its limit 2 / w (≈ 2) where s is tiny (no 0/0)
    factor = torch.where(s > 1e-12, angle / s.clamp_min(1e-300), 2.0 / w)
    return factor[..., None] * u


# numpy, for recorded and predicted poses (eval.pose_metrics, data.measured, the peers)


def rotate(quaternion: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Body-frame points (V, 3), or each frame's own (frames, V, 3), rotated by each frame's quaternion (frames, 4),
    w first: (frames, V, 3)."""
    w, u = quaternion[:, :1, None], quaternion[:, None, 1:]  # (F, 1, 1), (F, 1, 3)
    p = points if points.ndim == 3 else np.broadcast_to(points[None], (len(quaternion), *points.shape))
    t = 2.0 * np.cross(u, p)
    return p + w * t + np.cross(u, t)


def box_vertices(half_extents) -> np.ndarray:
    """The 8 corners (8, 3) of a box with these half-extents (3,) in its body frame (the box system's own)."""
    from diffcontact.systems.box import corners  # (box builds its states with this module)

    return corners(torch.as_tensor(np.asarray(half_extents, dtype=np.float64))).numpy()
