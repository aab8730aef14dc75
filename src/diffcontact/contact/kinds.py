"""Declared contact candidate kinds. Each holds index tensors built once and evaluates, batched,

    gap (B, K) in m (or rad for angle limits; < 0 means active), and Jacobian terms:
    cols (K, m) extended point indices and values (B, K, m, dc, d) so that row r of contact k is
    Σ_m values[:, k, m, r] placed at point cols[k, m] (normal row first, then tangent rows).

Extended point indices >= P are fixed anchors; their columns are dropped by the caller.
"""

from __future__ import annotations

import math

import torch

from diffcontact.contact.frames import point_weights, tangent_frame


def _body_points(body: torch.Tensor, q: int) -> torch.Tensor:
    return body[:, None] * q + torch.arange(q, device=body.device)[None, :]


class ContactKind:
    """Abstract candidate kind: ``count`` candidates, ``dc`` rows each, ``slot`` (K,) into μ and e."""

    count: int
    dc: int
    slot: torch.Tensor
    cols: torch.Tensor

    def evaluate(self, x: torch.Tensor, rows: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(gap (B, K), values (B, K, m, dc, d) or None) at extended positions x (B, P_ext, d)."""
        raise NotImplementedError


class SpherePairs(ContactKind):
    """Pairs of spheres (2D disks or 3D balls) of radii r_i, r_j centred on each body's first point.

    The normal points from body i to body j, so J v is the velocity of j relative to i (positive separates).
    """

    def __init__(self, body_i, body_j, radius_i, radius_j, slot, q: int, dc: int):
        self.pts_i, self.pts_j = _body_points(body_i, q), _body_points(body_j, q)
        self.ri, self.rj, self.slot, self.dc = radius_i, radius_j, slot, dc
        self.count = int(body_i.shape[0])
        self.cols = torch.cat([self.pts_i, self.pts_j], dim=1)

    def evaluate(self, x, rows):
        delta = x[:, self.pts_j[:, 0]] - x[:, self.pts_i[:, 0]]
        dist = delta.norm(dim=-1)
        gap = dist - (self.ri + self.rj).to(x)
        if not rows:
            return gap, None
        n = delta / dist[..., None]
        frame = tangent_frame(n, self.dc)  # (B, K, dc, d)
        wi = point_weights(x, self.pts_i, self.ri.to(x)[:, None] * n)
        wj = point_weights(x, self.pts_j, -self.rj.to(x)[:, None] * n)
        w = torch.cat([-wi, wj], dim=-1)  # (B, K, m)
        return gap, w[..., None, None] * frame[:, :, None]


class SpherePlanes(ContactKind):
    """Spheres against fixed planes (lines in 2D) n·y + c >= 0 with unit n pointing into the free side."""

    def __init__(self, body, normal, offset, radius, slot, q: int, dc: int):
        self.pts = _body_points(body, q)
        self.n, self.c, self.r, self.slot, self.dc = normal, offset, radius, slot, dc
        self.count = int(body.shape[0])
        self.cols = self.pts
        self.frame = tangent_frame(normal, dc)  # (K, dc, d), static

    def evaluate(self, x, rows):
        n = self.n.to(x)
        gap = (x[:, self.pts[:, 0]] * n).sum(-1) + self.c.to(x) - self.r.to(x)
        if not rows:
            return gap, None
        w = point_weights(x, self.pts, (-self.r.to(x)[:, None] * n).expand(x.shape[0], -1, -1))
        return gap, w[..., None, None] * self.frame.to(x)[None, :, None]


class DiskRimPlanes(ContactKind):
    """The rim of a 3D disk (radius R, centre at the body's centre + h e3, in the e1–e2 plane) vs planes.

    The lowest rim point is in closed form: with s_k = n·e_k and ρ = √(s1² + s2²), the rim angle has
    (cos a, sin a) = −(s1, s2)/ρ and the gap is n·(centre + h e3) + c − Rρ. (ρ is floored at 1e-12 for a
    disk lying flat against the plane, where every rim point is equally low.)
    """

    def __init__(self, body, normal, offset, radius, height, slot, dc: int):
        self.pts = _body_points(body, 4)
        self.n, self.c, self.R, self.h, self.slot, self.dc = normal, offset, radius, height, slot, dc
        self.count = int(body.shape[0])
        self.cols = self.pts
        self.frame = tangent_frame(normal, dc)

    def evaluate(self, x, rows):
        n = self.n.to(x)
        centre = x[:, self.pts[:, 0]]
        axes = x[:, self.pts[:, 1:]] - centre[:, :, None]  # (B, K, 3, d)
        s = (axes * n[:, None]).sum(-1)  # (B, K, 3)
        rho = (s[..., 0] ** 2 + s[..., 1] ** 2).clamp_min(1e-24).sqrt()
        h = self.h.to(x)
        gap = (centre * n).sum(-1) + h * s[..., 2] + self.c.to(x) - self.R.to(x) * rho
        if not rows:
            return gap, None
        cos_a, sin_a = -s[..., 0] / rho, -s[..., 1] / rho
        R = self.R.to(x)
        offset = h[:, None] * axes[..., 2, :] + R[:, None] * (
            cos_a[..., None] * axes[..., 0, :] + sin_a[..., None] * axes[..., 1, :]
        )
        w = point_weights(x, self.pts, offset)
        return gap, w[..., None, None] * self.frame.to(x)[None, :, None]


class VertexPlanes(ContactKind):
    """Vertices of 3-D extended bodies (body-frame coordinates b, m) against fixed planes n·y + c >= 0.

    The vertex is c + Σ_k b_k (x_k − c) (x_0 = c the centre, x_k the axis points), linear in the body's points with
    the constant weights [1 − Σ b_k, b_k], so gap = n·vertex + c and its rows are those weights times the plane's
    frame.
    """

    def __init__(self, body, vertex, normal, offset, slot, dc: int):
        self.pts = _body_points(body, 4)
        self.n, self.c, self.slot, self.dc = normal, offset, slot, dc
        self.count = int(body.shape[0])
        self.cols = self.pts
        self.weights = torch.cat([1.0 - vertex.sum(-1, keepdim=True), vertex], dim=-1)  # (K, 4)
        self.frame = tangent_frame(normal, dc)

    def evaluate(self, x, rows):
        w = self.weights.to(x)
        vertex = (w[None, :, :, None] * x[:, self.pts]).sum(2)  # (B, K, d)
        gap = (vertex * self.n.to(x)).sum(-1) + self.c.to(x)
        if not rows:
            return gap, None
        vals = w[:, :, None, None] * self.frame.to(x)[:, None]  # (K, 4, dc, d)
        return gap, vals.expand(x.shape[0], *vals.shape)


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


class AngleLimits(ContactKind):
    """2D bend limits between consecutive links a→b and b→c: gap = limit − s Δq, s = ±1 (both sides).

    Link angles q = atan2(Δx, −Δy) from the downward vertical, Δq = q_bc − q_ab wrapped to (−π, π] (rad).
    Rows are ∇gap (a 1-D contact space: normal only, frictionless).
    """

    def __init__(self, a, b, c, limit, side, slot):
        self.a, self.b, self.cc, self.limit, self.side, self.slot = a, b, c, limit, side, slot
        self.dc, self.count = 1, int(a.shape[0])
        self.cols = torch.stack([a, b, c], dim=1)

    @staticmethod
    def _angle(link):
        return torch.atan2(link[..., 0], -link[..., 1])

    def evaluate(self, x, rows):
        l1 = x[:, self.b] - x[:, self.a]
        l2 = x[:, self.cc] - x[:, self.b]
        dq = _wrap(self._angle(l2) - self._angle(l1))
        s = self.side.to(x)
        gap = self.limit.to(x) - s * dq
        if not rows:
            return gap, None
        g1 = torch.stack([-l1[..., 1], l1[..., 0]], -1) / (l1 * l1).sum(-1, keepdim=True)  # ∇ q_ab
        g2 = torch.stack([-l2[..., 1], l2[..., 0]], -1) / (l2 * l2).sum(-1, keepdim=True)
        s = s[:, None]
        vals = torch.stack([-s * g1, s * (g1 + g2), -s * g2], dim=2)  # (B, K, 3, d)
        return gap, vals[:, :, :, None, :]


class StretchLimits(ContactKind):
    """Length limits of links a→b: side +1 gap = L_max − |l|, side −1 gap = |l| − L_min (m)."""

    def __init__(self, a, b, bound, side, slot):
        self.a, self.b, self.bound, self.side, self.slot = a, b, bound, side, slot
        self.dc, self.count = 1, int(a.shape[0])
        self.cols = torch.stack([a, b], dim=1)

    def evaluate(self, x, rows):
        link = x[:, self.b] - x[:, self.a]
        length = link.norm(dim=-1)
        s = self.side.to(x)
        gap = s * (self.bound.to(x) - length)
        if not rows:
            return gap, None
        u = link / length[..., None]
        vals = torch.stack([s[:, None] * u, -s[:, None] * u], dim=2)
        return gap, vals[:, :, :, None, :]
