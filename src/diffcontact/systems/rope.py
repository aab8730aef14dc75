"""Rope (the paper's task): n nodes of point mass hanging from a fixed anchor, Hooke springs on the links, and
joint limits on bending (|Δq| <= bend_limit) and stretching (stretch_min l0 <= |link| <= stretch_max l0).

Limit slots: bend limit i (between links i and i+1) is slot i, stretch of link j is slot n−1+j; both sides
of a limit share its slot. Limits have a 1-D contact space (normal only), so the solver runs with d = 1.
"""

from __future__ import annotations

import math

import torch

from diffcontact.config import TaskConfig
from diffcontact.contact.detect import Detector
from diffcontact.contact.kinds import AngleLimits, StretchLimits
from diffcontact.dynamics.potentials import Gravity, Springs, SumPotential
from diffcontact.errors import ConfigError
from diffcontact.state import Inertia, Params, State
from diffcontact.systems.base import Drawing, Links, System, Task
from diffcontact.systems.common import F64, coefficients, make_constraints, rejection_sample
from diffcontact.systems.pendulum import chain_points

TABLES = {
    "rope": ("nodes", "mass", "rest_length", "spring_k", "bend_limit", "stretch_min", "stretch_max"),
    "potential": ("gravity",),
    "init": ("angle_range", "bend_spread", "angular_velocity_std"),
}


def build_rope(cfg: TaskConfig) -> Task:
    """Rope from ``[rope]`` (nodes, mass, rest_length, spring_k, bend_limit, stretch_min, stretch_max)."""
    sec = cfg.section("rope")
    n = sec.integer("nodes", lo=2)
    mass = sec.number("mass", lo=0.0, lo_open=True)
    l0 = sec.number("rest_length", lo=0.0, lo_open=True)
    k = sec.number("spring_k", lo=0.0)
    bend = sec.number("bend_limit", lo=0.0, lo_open=True, hi=math.pi)
    s_min = sec.number("stretch_min", lo=0.0, lo_open=True)
    s_max = sec.number("stretch_max", lo=0.0, lo_open=True)
    if s_max <= 1.0 or s_min >= 1.0:
        raise ConfigError(f"rope.stretch_min = {s_min:g} and rope.stretch_max = {s_max:g} must bracket 1")
    d = 2
    n_slots = 2 * n - 1
    mu, e = coefficients(cfg, n_slots)
    anchors = torch.zeros(1, d, dtype=F64)
    prev = torch.cat([torch.tensor([n]), torch.arange(n - 1)])  # link j joins prev[j] -> j (n = anchor)
    nodes = torch.arange(n)
    side = torch.tensor([1.0, -1.0], dtype=F64)
    b_idx = torch.arange(n - 1).repeat_interleave(2)
    s_idx = torch.arange(n).repeat_interleave(2)
    kinds = (
        AngleLimits(
            prev[b_idx],
            nodes[b_idx],
            nodes[b_idx] + 1,
            torch.full((2 * (n - 1),), bend, dtype=F64),
            side.repeat(n - 1),
            b_idx,
        ),
        StretchLimits(
            prev[s_idx],
            nodes[s_idx],
            torch.tensor([s_max, s_min], dtype=F64).repeat(n) * l0,
            side.repeat(n),
            n - 1 + s_idx,
        ),
    )
    system = System(
        name=cfg.name,
        d=d,
        n_bodies=n,
        points_per_body=1,
        anchors=anchors,
        constraints=make_constraints(n, d, anchors),
        detector=Detector(kinds, n, anchors, d),
        n_slots=n_slots,
        drawing=Drawing(
            radii=torch.full((n,), 0.2 * l0, dtype=F64),
            segments=torch.stack([prev, nodes], 1),
            plane_normal=torch.zeros(0, d, dtype=F64),
            plane_offset=torch.zeros(0, dtype=F64),
            shape="ball",
            view=((-1.1 * n * l0, 1.1 * n * l0), (-1.1 * n * l0, 1.1 * n * l0)),
        ),
        links=Links(
            prev, nodes, torch.full((n,), l0, dtype=F64), torch.full((n,), (s_max - 1.0) * l0, dtype=F64), anchors
        ),
    )
    g = cfg.section("potential").number("gravity", 9.81, lo=0.0)
    m = torch.full((n,), mass, dtype=F64)
    springs = Springs(prev, nodes, torch.full((n,), l0, dtype=F64), torch.full((n,), k, dtype=F64), anchors)
    params = Params(
        Inertia(m, torch.zeros(n, 0, dtype=F64)),
        SumPotential(springs, Gravity(g, torch.tensor([0.0, 1.0], dtype=F64), 1)),
        mu,
        e,
    )
    init = cfg.section("init")
    q_lo, q_hi = init.numbers("angle_range", length=2, default=[0.0, math.pi])
    spread = init.number("bend_spread", bend, lo=0.0)
    w_std = init.number("angular_velocity_std", 1.0, lo=0.0)
    ell = torch.full((n,), l0, dtype=F64)

    def sample(count: int, gen: torch.Generator, dtype: torch.dtype) -> State:
        def draw(kk: int) -> State:
            q0 = q_lo + (q_hi - q_lo) * torch.rand(kk, 1, generator=gen, dtype=F64)
            dq = spread * (2 * torch.rand(kk, n - 1, generator=gen, dtype=F64) - 1)
            q = torch.cat([q0, q0 + dq.cumsum(1)], dim=1)
            w = w_std * torch.randn(kk, n, generator=gen, dtype=F64)
            return State(*chain_points(anchors[0], ell, q, w))

        state = rejection_sample(draw, system.detector.gaps, count, cfg.name)
        return State(state.x.to(dtype), state.v.to(dtype))

    return Task(cfg, system, params, sample)
