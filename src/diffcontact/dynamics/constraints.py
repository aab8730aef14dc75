"""Holonomic equality constraints Φ(x) = 0 and their Jacobians J_E = ∂Φ/∂x, batched and in closed form.

Two declared kinds cover every benchmark system:
- distance constraints |x_i − x_j|² − L² = 0 between extended point indices i, j (an index >= P is a fixed
  anchor: a pendulum pivot); rigid extended bodies use them between their points;
- linear (ball-joint) constraints Σ_p w_p x_p − a = 0 (d scalar rows each), e.g. a gyroscope pivot.
Positions are (B, P, d); Jacobians are (B, E, D) with D = P d in the flattened (P, d) layout.
"""

from __future__ import annotations

import torch

from diffcontact.state import with_anchors


class Constraints:
    """The equality constraints of a system (static index tensors, built once).

    dist_i, dist_j: (E1,) extended point indices; dist_len: (E1,) lengths in m; anchors: (n_anchors, d);
    joint_pts: (n_joints, q) point indices; joint_w: (n_joints, q) weights; joint_at: (n_joints, d) positions.
    E = E1 + d n_joints scalar rows.
    """

    def __init__(
        self,
        n_points: int,
        d: int,
        anchors: torch.Tensor,
        dist_i: torch.Tensor,
        dist_j: torch.Tensor,
        dist_len: torch.Tensor,
        joint_pts: torch.Tensor,
        joint_w: torch.Tensor,
        joint_at: torch.Tensor,
    ):
        self.P, self.d = n_points, d
        self.anchors = anchors
        self.dist_i, self.dist_j, self.dist_len = dist_i, dist_j, dist_len
        self.joint_pts, self.joint_w, self.joint_at = joint_pts, joint_w, joint_at
        self.n_dist = int(dist_i.shape[0])
        self.n_joint = int(joint_pts.shape[0])
        self.count = self.n_dist + d * self.n_joint
        # signed incidence (E1, P): +1 at i, −1 at j (anchor columns dropped), so a row is S ⊗ 2(x_i − x_j)
        n_ext = n_points + anchors.shape[0]
        inc = torch.zeros(self.n_dist, n_ext, dtype=dist_len.dtype, device=dist_len.device)
        inc[torch.arange(self.n_dist, device=dist_i.device), dist_i] += 1.0
        inc[torch.arange(self.n_dist, device=dist_j.device), dist_j] -= 1.0
        self._incidence = inc[:, :n_points]
        self._joint_jac = self._joint_rows()  # (d n_joint, D), constant

    def _joint_rows(self) -> torch.Tensor:
        J = torch.zeros(self.n_joint, self.d, self.P, self.d, dtype=self.joint_w.dtype, device=self.joint_w.device)
        if self.n_joint:
            q = self.joint_pts.shape[1]
            joint = torch.arange(self.n_joint, device=self.joint_pts.device)[:, None].expand(-1, q)
            for a in range(self.d):  # build-time only: d <= 3 axes
                J[joint, a, self.joint_pts, a] = self.joint_w
        return J.reshape(self.n_joint * self.d, self.P * self.d)

    def _ext(self, x: torch.Tensor) -> torch.Tensor:
        return with_anchors(x, self.anchors)

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

    def project(
        self, x: torch.Tensor, v: torch.Tensor, tol: float, steps: int = 50
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """x, v (B, P, d) moved onto the constraints: positions by Gauss–Newton steps of least norm until
        max |Φ| < ``tol``, then velocities onto J_E v = 0 (the orthogonal projection).  Raises FloatingPointError
        where ``steps`` steps do not reach ``tol``."""
        B, P, d = x.shape
        residual = float("nan")  # (max |Φ| of the last step's start)
        for _ in range(steps):
            phi = self.phi(x)  # (B, E)
            residual = float(phi.abs().max())
            if residual < tol:
                break
            J = self.jac(x)  # (B, E, D)
            step = J.transpose(1, 2) @ torch.linalg.solve(J @ J.transpose(1, 2), phi[..., None])
            x = x - step.reshape(B, P, d)
        else:
            raise FloatingPointError(f"projection onto the constraints did not converge (|Φ| = {residual:.1e})")
        J = self.jac(x)
        flat = v.reshape(B, P * d, 1)
        flat = flat - J.transpose(1, 2) @ torch.linalg.solve(J @ J.transpose(1, 2), J @ flat)
        return x, flat.reshape(B, P, d)

    def jac_dot(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """∂(J_E v)/∂x (B, E, D); its product with v is the J̇_E v term of the constrained dynamics."""
        return self._pair_rows(x, v, 0.0)

    def _pair_rows(self, x: torch.Tensor, y: torch.Tensor, joint_value: float | None) -> torch.Tensor:
        B = x.shape[0]
        parts = []
        if self.n_dist:
            ext = self._ext(y) if y is x else torch.cat([y, y.new_zeros(B, self.anchors.shape[0], self.d)], 1)
            delta = 2.0 * (ext[:, self.dist_i] - ext[:, self.dist_j])  # (B, E1, d)
            rows = self._incidence.to(x)[None, :, :, None] * delta[:, :, None, :]  # (B, E1, P, d)
            parts.append(rows.reshape(B, self.n_dist, self.P * self.d))
        if self.n_joint:
            J = self._joint_jac.to(x)
            parts.append((J if joint_value is None else torch.zeros_like(J)).expand(B, -1, -1))
        return torch.cat(parts, dim=1) if parts else x.new_zeros(B, 0, self.P * self.d)
