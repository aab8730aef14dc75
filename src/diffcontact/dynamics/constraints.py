"""Holonomic equality constraints Φ(x) = 0 and their Jacobians J_E = ∂Φ/∂x, batched and in closed form.

Two declared kinds cover every benchmark system:
- distance constraints |x_i − x_j|² − L² = 0 between extended point indices i, j (an index >= P is a fixed
  anchor: a pendulum pivot); rigid extended bodies use them between their points;
- linear (ball-joint) constraints Σ_p w_p x_p − a = 0 (d scalar rows each), e.g. a gyroscope pivot.
Positions are (B, P, d); Jacobians are (B, E, D) with D = P d in the flattened (P, d) layout.
"""

from __future__ import annotations

import torch


def _scatter_rows(n_rows: int, n_ext: int, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor,
                  P: int) -> torch.Tensor:
    """Dense rows (B, R, P d) from values (B, R, m, d) placed at extended points ``cols`` (R, m).

    Columns of anchors (index >= P) are dropped. ``rows`` (R, m) repeats the row index. Differentiable.
    """
    B, _, _, d = values.shape
    out = values.new_zeros(n_rows, n_ext, B, d)
    out = out.index_put((rows, cols), values.permute(1, 2, 0, 3))
    return out[:, :P].permute(2, 0, 1, 3).reshape(B, n_rows, P * d)


class Constraints:
    """The equality constraints of a system (static index tensors, built once).

    dist_i, dist_j: (E1,) extended point indices; dist_len: (E1,) lengths in m; anchors: (n_anchors, d);
    joint_pts: (n_joints, q) point indices; joint_w: (n_joints, q) weights; joint_at: (n_joints, d) positions.
    E = E1 + d n_joints scalar rows.
    """

    def __init__(self, n_points: int, d: int, anchors: torch.Tensor, dist_i: torch.Tensor,
                 dist_j: torch.Tensor, dist_len: torch.Tensor, joint_pts: torch.Tensor,
                 joint_w: torch.Tensor, joint_at: torch.Tensor):
        self.P, self.d = n_points, d
        self.anchors = anchors
        self.dist_i, self.dist_j, self.dist_len = dist_i, dist_j, dist_len
        self.joint_pts, self.joint_w, self.joint_at = joint_pts, joint_w, joint_at
        self.n_dist = int(dist_i.shape[0])
        self.n_joint = int(joint_pts.shape[0])
        self.count = self.n_dist + d * self.n_joint
        self._rows2 = torch.arange(self.n_dist)[:, None].expand(-1, 2)
        self._cols2 = torch.stack([dist_i, dist_j], dim=-1) if self.n_dist else dist_i.new_zeros(0, 2)
        self._joint_jac = self._joint_rows()  # (d n_joint, D), constant

    def _joint_rows(self) -> torch.Tensor:
        J = torch.zeros(self.n_joint, self.d, self.P, self.d, dtype=self.joint_w.dtype)
        if self.n_joint:
            q = self.joint_pts.shape[1]
            for a in range(self.d):  # build-time only: d <= 3 axes
                J[torch.arange(self.n_joint)[:, None].expand(-1, q), a, self.joint_pts, a] = self.joint_w
        return J.reshape(self.n_joint * self.d, self.P * self.d)

    def _ext(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x, self.anchors.to(x).expand(x.shape[0], -1, -1)], dim=1)

    def phi(self, x: torch.Tensor) -> torch.Tensor:
        """Constraint values Φ(x): (B, P, d) -> (B, E), in m² (distances) and m (joints)."""
        parts = []
        if self.n_dist:
            ext = self._ext(x)
            delta = ext[:, self.dist_i] - ext[:, self.dist_j]
            parts.append((delta * delta).sum(-1) - self.dist_len.to(x) ** 2)
        if self.n_joint:
            pos = (x[:, self.joint_pts] * self.joint_w.to(x)[None, :, :, None]).sum(2)
            parts.append((pos - self.joint_at.to(x)).reshape(x.shape[0], -1))
        return torch.cat(parts, dim=-1) if parts else x.new_zeros(x.shape[0], 0)

    def jac(self, x: torch.Tensor) -> torch.Tensor:
        """J_E = ∂Φ/∂x: (B, P, d) -> (B, E, D)."""
        return self._pair_rows(x, x, None)

    def jac_dot(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """∂(J_E v)/∂x (B, E, D); its product with v is the J̇_E v term of the constrained dynamics."""
        return self._pair_rows(x, v, 0.0)

    def _pair_rows(self, x: torch.Tensor, y: torch.Tensor, joint_value: float | None) -> torch.Tensor:
        B = x.shape[0]
        parts = []
        if self.n_dist:
            ext = self._ext(y) if y is x else torch.cat([y, y.new_zeros(B, self.anchors.shape[0], self.d)], 1)
            delta = 2.0 * (ext[:, self.dist_i] - ext[:, self.dist_j])  # (B, E1, d)
            values = torch.stack([delta, -delta], dim=2)  # (B, E1, 2, d)
            parts.append(_scatter_rows(self.n_dist, self.P + self.anchors.shape[0], self._rows2,
                                       self._cols2, values, self.P))
        if self.n_joint:
            J = self._joint_jac.to(x)
            parts.append((J if joint_value is None else torch.zeros_like(J)).expand(B, -1, -1))
        return torch.cat(parts, dim=1) if parts else x.new_zeros(B, 0, self.P * self.d)
