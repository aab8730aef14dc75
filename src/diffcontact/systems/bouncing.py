"""Bouncing point masses (BP), bouncing disks (BD) and the billiards table: bodies in a box of walls, in 2-D, or
balls in a box of planes in 3-D (``bodies.dim = 3``).

Contact slots (the published order): the n(n−1)/2 pairs first, in lexicographic order, then ball–wall contacts at
n(n−1)/2 + n_walls·ball + wall. Disks are extended bodies (3 points, moments r²/4 per unit mass). Gravity acts
along −y in 2-D and along −z in 3-D.
"""

from __future__ import annotations

import math

import torch

from diffcontact.config import TaskConfig
from diffcontact.contact.detect import Detector
from diffcontact.contact.kinds import SpherePairs, SpherePlanes
from diffcontact.dynamics.potentials import Gravity, SumPotential
from diffcontact.errors import ConfigError
from diffcontact.state import Inertia, Params, State
from diffcontact.systems.base import Drawing, System, Task
from diffcontact.systems.common import (
    F64,
    check_lengths,
    coefficients,
    make_constraints,
    pairs,
    planes,
    rejection_sample,
    rigid_body_distances,
)

BOX = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 1.0], [0.0, -1.0, 1.0]]
BOX3 = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
BOX3 += [[-1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 1.0], [0.0, 0.0, -1.0, 1.0]]  # the unit cube
TABLES = {
    "bodies": ("kind", "dim", "masses", "radii"),
    "walls": ("lines", "planes"),
    "potential": ("gravity",),
    "init": ("kind", "box", "velocity_std", "angular_velocity_std", "cue_position", "cue_velocity", "goal"),
}


def build_bouncing(cfg: TaskConfig) -> Task:
    """BP / BD / billiards from ``[bodies]`` (kind, dim, masses, radii), ``[walls]`` (``lines`` [a, b, c] in 2-D,
    ``planes`` [a, b, c, e] in 3-D, free where a x + b y (+ c z) + last >= 0), ``[potential]``, ``[contact]``."""
    bodies = cfg.section("bodies")
    kind = bodies.choice("kind", ("point", "disk"))
    d = bodies.integer("dim", 2, lo=2)
    if d not in (2, 3) or (d == 3 and kind != "point"):
        raise ConfigError(f"bodies.dim = {d} is not 2 (points or disks) or 3 (points: balls)")
    masses = bodies.numbers("masses", lo=0.0, lo_open=True, nonempty=True)
    n = len(masses)
    radii = bodies.numbers("radii", lo=0.0, lo_open=True)
    check_lengths(bodies, "radii", radii, n)
    q = 1 if kind == "point" else d + 1
    walls = cfg.section("walls")
    key, other = ("lines", "planes") if d == 2 else ("planes", "lines")
    if walls.has(other):
        raise ConfigError(f"walls.{other} is for {5 - d}-D bodies; in {d}-D give walls.{key} ({d + 1} numbers a row)")
    wall_n, wall_c = planes(walls, key, d, default=BOX if d == 2 else BOX3)
    n_walls = wall_n.shape[0]
    pi, pj = pairs(n)
    n_pairs = pi.numel()
    n_slots = n_pairs + n * n_walls
    mu, e = coefficients(cfg, n_slots)
    r = torch.tensor(radii, dtype=F64)
    m = torch.tensor(masses, dtype=F64)
    moments = (r[:, None] ** 2 / 4).expand(n, d).clone() if kind == "disk" else torch.zeros(n, 0, dtype=F64)
    ball = torch.arange(n).repeat_interleave(n_walls)
    wall = torch.arange(n_walls).repeat(n)
    kinds = (
        SpherePairs(pi, pj, r[pi], r[pj], torch.arange(n_pairs), q, dc=d),
        SpherePlanes(ball, wall_n[wall], wall_c[wall], r[ball], n_pairs + torch.arange(n * n_walls), q, dc=d),
    )
    anchors = torch.zeros(0, d, dtype=F64)
    dist = rigid_body_distances(n, d) if kind == "disk" else None
    P = n * q
    system = System(
        name=cfg.name,
        d=d,
        n_bodies=n,
        points_per_body=q,
        anchors=anchors,
        constraints=make_constraints(P, d, anchors, dist=dist),
        detector=Detector(kinds, P, anchors, d),
        n_slots=n_slots,
        drawing=Drawing(
            radii=r,
            segments=torch.zeros(0, 2, dtype=torch.long),
            plane_normal=wall_n,
            plane_offset=wall_c,
            shape="ball" if kind == "point" else "disk2d",
            view=_view(cfg, d),
        ),
    )
    pot = cfg.section("potential")
    g = pot.number("gravity", 0.0, lo=0.0)
    potential = SumPotential(Gravity(g, torch.eye(d, dtype=F64)[d - 1], q)) if g else SumPotential()
    params = Params(Inertia(m, moments), potential, mu, e)
    init = cfg.section("init")
    if init.choice("kind", ("uniform", "billiards"), default="uniform") == "billiards":
        if d != 2:
            raise ConfigError("init.kind = 'billiards' is a 2-D layout (bodies.dim = 2)")
        sampler = _billiards_sampler(cfg, n, r)
    else:
        sampler = _box_sampler(cfg, system, kind)
    return Task(cfg, system, params, sampler)


def _view(cfg: TaskConfig, d: int) -> tuple[tuple[float, float], ...]:
    """``init.box``: (lo, hi) per axis, default the unit square or cube."""
    box = cfg.section("init").matrix("box", cols=2, default=[[0.0, 1.0]] * d)
    if len(box) != d or any(lo >= hi for lo, hi in box):
        raise ConfigError(f"init.box = {box} is not {d} rows [lo, hi] with lo < hi")
    return tuple((lo, hi) for lo, hi in box)


def disk_points(
    centre: torch.Tensor, theta: torch.Tensor, v: torch.Tensor, omega: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Points (c, c + e1, c + e2) and their velocities of 2D disks: centre, v (B, n, 2); θ, ω (B, n).

    e1, e2 are the columns of R(θ) and Ṙ = ω [[0, −1], [1, 0]] R.
    """
    c, s = torch.cos(theta), torch.sin(theta)
    e1, e2 = torch.stack([c, s], -1), torch.stack([-s, c], -1)
    de1, de2 = omega[..., None] * e2, -omega[..., None] * e1
    x = torch.stack([centre, centre + e1, centre + e2], dim=2).flatten(1, 2)
    vel = torch.stack([v, v + de1, v + de2], dim=2).flatten(1, 2)
    return x, vel


def _box_sampler(cfg: TaskConfig, system: System, kind: str):
    init = cfg.section("init")
    d = system.d
    lo, hi = torch.tensor(_view(cfg, d), dtype=F64).unbind(1)
    v_std = init.number("velocity_std", 1.0, lo=0.0)
    w_std = init.number("angular_velocity_std", 0.5, lo=0.0)
    n = system.n_bodies

    def sample(count: int, gen: torch.Generator, dtype: torch.dtype) -> State:
        def draw(k: int) -> State:
            centre = lo + (hi - lo) * torch.rand(k, n, d, generator=gen, dtype=F64)
            if kind == "point":
                return State(centre, torch.zeros_like(centre))
            theta = 2 * math.pi * torch.rand(k, n, generator=gen, dtype=F64)
            return State(*disk_points(centre, theta, torch.zeros_like(centre), torch.zeros_like(theta)))

        state = rejection_sample(draw, system.detector.gaps, count, cfg.name)
        vel = v_std * torch.randn(count, n, d, generator=gen, dtype=F64)
        if kind == "point":
            return State(state.x.to(dtype), vel.to(dtype))
        omega = w_std * torch.randn(count, n, generator=gen, dtype=F64)
        centre = state.x[:, ::3]
        e1 = state.x[:, 1::3] - centre
        theta = torch.atan2(e1[..., 1], e1[..., 0])
        x, v = disk_points(centre, theta, vel, omega)
        return State(x.to(dtype), v.to(dtype))

    return sample


def _billiards_sampler(cfg: TaskConfig, n: int, r: torch.Tensor):
    """The billiards layout (the paper's): cue ball at ``init.cue_position`` with ``init.cue_velocity``, the
    others at rest in a triangle, layer i slot j at (0.5 + 2r i, 0.5 + 2r j − 0.7 r i). Deterministic."""
    init = cfg.section("init")
    cue_x = init.numbers("cue_position", length=2, default=[0.1, 0.5])
    cue_v = init.numbers("cue_velocity", length=2, default=[0.3, 0.0])
    rad = float(r[0])
    pos = [cue_x]
    layer = 0
    while len(pos) < n:
        for j in range(layer + 1):
            if len(pos) < n:
                pos.append([0.5 + 2 * rad * layer, 0.5 + 2 * rad * j - 0.7 * rad * layer])
        layer += 1
    x0 = torch.tensor(pos, dtype=F64)
    v0 = torch.zeros_like(x0)
    v0[0] = torch.tensor(cue_v, dtype=F64)
    if (r != r[0]).any():
        raise ConfigError("bodies.radii must be equal for the billiards layout")

    def sample(count: int, gen: torch.Generator, dtype: torch.dtype) -> State:
        return State(x0.expand(count, -1, -1).to(dtype).clone(), v0.expand(count, -1, -1).to(dtype).clone())

    return sample
