"""Chain pendulum with contacts (CP): point masses linked by rigid rods, the first tethered to a pivot.

Constraints |x_0 − pivot|² = l_0², |x_i − x_{i−1}|² = l_i². Each mass is drawn as a disk of its radius and
can hit the walls/ground ``walls.lines``; slot of (mass i, wall w) = n_walls·i + w (one ground: slot = i).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch

from diffcontact.config import TaskConfig
from diffcontact.contact.detect import Detector
from diffcontact.contact.kinds import SpherePlanes
from diffcontact.dynamics.potentials import Gravity, SumPotential
from diffcontact.state import Inertia, Params, State
from diffcontact.systems.base import Drawing, System, Task
from diffcontact.systems.common import F64, check_lengths, coefficients, make_constraints, planes, rejection_sample

TABLES = {
    "bodies": ("masses", "radii"),
    "pendulum": ("lengths", "pivot"),
    "walls": ("lines",),
    "potential": ("gravity",),
    "init": ("angle_range", "angular_velocity_std"),
}


def build_chain_pendulum(cfg: TaskConfig) -> Task:
    """CP from ``[bodies]`` (masses, radii), ``[pendulum]`` (lengths, pivot), ``[walls]``, ``[potential]``."""
    bodies = cfg.section("bodies")
    masses = bodies.numbers("masses", lo=0.0, lo_open=True, nonempty=True)
    n = len(masses)
    radii = bodies.numbers("radii", lo=0.0, lo_open=True)
    check_lengths(bodies, "radii", radii, n)
    pend = cfg.section("pendulum")
    lengths = pend.numbers("lengths", lo=0.0, lo_open=True)
    check_lengths(pend, "lengths", lengths, n)
    pivot = torch.tensor(pend.numbers("pivot", length=2, default=[0.0, 0.0]), dtype=F64)
    d = 2
    wall_n, wall_c = planes(cfg.section("walls"), "lines", d, default=[[0.0, 1.0, 1.0]])
    n_walls = wall_n.shape[0]
    n_slots = n * n_walls
    mu, e = coefficients(cfg, n_slots)
    r = torch.tensor(radii, dtype=F64)
    m = torch.tensor(masses, dtype=F64)
    anchors = pivot[None]
    i = torch.arange(n)
    j = torch.cat([torch.tensor([n]), torch.arange(n - 1)])  # mass 0 to the pivot (extended index n)
    dist = (i, j, torch.tensor(lengths, dtype=F64))
    ball = torch.arange(n).repeat_interleave(n_walls)
    wall = torch.arange(n_walls).repeat(n)
    kinds = (SpherePlanes(ball, wall_n[wall], wall_c[wall], r[ball], torch.arange(n_slots), 1, dc=d),)
    reach = sum(lengths) + max(radii)
    system = System(
        name=cfg.name,
        d=d,
        n_bodies=n,
        points_per_body=1,
        anchors=anchors,
        constraints=make_constraints(n, d, anchors, dist=dist),
        detector=Detector(kinds, n, anchors, d),
        n_slots=n_slots,
        noise_coordinates=ChainAngles(pivot, torch.tensor(lengths, dtype=F64)),
        drawing=Drawing(
            radii=r,
            segments=torch.stack([j, i], 1),
            plane_normal=wall_n,
            plane_offset=wall_c,
            shape="ball",
            view=((-reach, reach), (-reach, reach)),
        ),
    )
    g = cfg.section("potential").number("gravity", 9.81, lo=0.0)
    params = Params(
        Inertia(m, torch.zeros(n, 0, dtype=F64)),
        SumPotential(Gravity(g, torch.tensor([0.0, 1.0], dtype=F64), 1)),
        mu,
        e,
    )
    init = cfg.section("init")
    q_lo, q_hi = init.numbers("angle_range", length=2, default=[0.0, math.pi])
    w_std = init.number("angular_velocity_std", 1.0, lo=0.0)
    ell = torch.tensor(lengths, dtype=F64)

    def sample(count: int, gen: torch.Generator, dtype: torch.dtype) -> State:
        def draw(k: int) -> State:
            q = q_lo + (q_hi - q_lo) * torch.rand(k, n, generator=gen, dtype=F64)
            w = w_std * torch.randn(k, n, generator=gen, dtype=F64)
            return State(*chain_points(pivot, ell, q, w))

        state = rejection_sample(draw, system.detector.gaps, count, cfg.name)
        return State(state.x.to(dtype), state.v.to(dtype))

    return Task(cfg, system, params, sample)


@dataclass(frozen=True)
class ChainAngles:
    """The chain pendulum's noise coordinates (``systems.base.NoiseCoordinates``): the absolute link angles q
    (rad, from the downward vertical) and their rates w (rad/s), (B, n), of a chain of links ``lengths`` (n,) in m
    hanging from ``pivot`` (2,) in m."""

    pivot: torch.Tensor
    lengths: torch.Tensor
    name: ClassVar[str] = "chain"

    @property
    def size(self) -> int:
        """The number of links (of angles, and of rates)."""
        return int(self.lengths.shape[0])

    def from_cartesian(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q, w (B, n) of node positions and velocities x, v (B, n, 2) on the chain."""
        prev_x = torch.cat([self.pivot.to(x).expand(x.shape[0], 1, 2), x[:, :-1]], 1)
        prev_v = torch.cat([torch.zeros_like(v[:, :1]), v[:, :-1]], 1)
        link, dlink = x - prev_x, v - prev_v  # (B, n, 2)
        q = torch.atan2(link[..., 0], -link[..., 1])
        w = (dlink * torch.stack([torch.cos(q), torch.sin(q)], -1)).sum(-1) / self.lengths.to(x)
        return q, w

    def to_cartesian(self, q: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x, v (B, n, 2) of link angles and rates q, w (B, n)."""
        return chain_points(self.pivot.to(q), self.lengths.to(q), q, w)


def chain_points(
    pivot: torch.Tensor, lengths: torch.Tensor, q: torch.Tensor, w: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Node positions and velocities (B, n, 2) of a chain from absolute link angles q (from the downward
    vertical) and rates w (B, n): link l (sin q, −cos q), its velocity l q̇ (cos q, sin q), summed."""
    link = lengths * torch.stack([torch.sin(q), -torch.cos(q)], -1).movedim(-1, 0)
    dlink = lengths * w * torch.stack([torch.cos(q), torch.sin(q)], -1).movedim(-1, 0)
    x = pivot + link.movedim(0, -1).cumsum(dim=1)
    v = dlink.movedim(0, -1).cumsum(dim=1)
    return x, v
