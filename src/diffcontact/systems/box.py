"""A rigid box tossed onto planes: one 3-D extended body (4 points) whose 8 corners touch the planes.

The body's first point is the box's centre; its centre of mass is ``centre_of_mass`` (3,) m from it in the body
frame (default 0: a uniform box), and a learned model learns it. ``half_extents`` (3,) m give its corners (±a, ±b,
±c) in the body frame, about the box's centre. Every corner against every plane is a contact candidate
(VertexPlanes, 3-D friction cones), one μ and e slot per plane. The initial states are tosses: a uniformly random
orientation, the centre at a height in ``init.height`` above the first plane's origin, a horizontal speed in
``init.speed`` in a random direction, a vertical speed in ``init.vertical_speed`` and a spin of magnitude in
``init.spin`` about a random axis."""

from __future__ import annotations

import math

import torch

from diffcontact.config import TaskConfig
from diffcontact.contact.detect import Detector
from diffcontact.contact.kinds import VertexPlanes
from diffcontact.dynamics.potentials import Gravity, SumPotential
from diffcontact.errors import ConfigError
from diffcontact.state import Inertia, Params, State
from diffcontact.systems.base import Drawing, System, Task
from diffcontact.systems.common import (
    F64,
    coefficients,
    make_constraints,
    planes,
    rejection_sample,
    rigid_body_distances,
)
from diffcontact.systems.poses import pose_to_points

TABLES = {
    "body": ("mass", "moments", "half_extents", "centre_of_mass"),
    "walls": ("planes",),
    "potential": ("gravity",),
    "init": ("height", "speed", "vertical_speed", "spin"),
}


def corners(half_extents: torch.Tensor) -> torch.Tensor:
    """The 8 corners (8, 3) of a box with half-extents (3,) in its body frame, x slowest."""
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=F64)
    return signs * half_extents


def _range(sec, key: str, default: tuple[float, float], lo: float | None = None) -> tuple[float, float]:
    pair = sec.numbers(key, length=2, lo=lo) if sec.has(key) else list(default)
    if pair[0] > pair[1]:
        raise ConfigError(f"{sec.prefix}.{key} = {pair} must be [low, high] with low <= high")
    return pair[0], pair[1]


def build_box(cfg: TaskConfig) -> Task:
    """A tossed box from ``[body]`` (mass kg, moments (3,) m² per unit mass about the centre of mass, half_extents
    (3,) m, centre_of_mass (3,) m from the box's centre, default 0), ``[walls]``
    (planes [n_x, n_y, n_z, c], free where n·y + c >= 0), ``[potential]`` (gravity along −z, m/s²), ``[init]``."""
    body = cfg.section("body")
    mass = body.number("mass", lo=0.0, lo_open=True)
    moments = body.numbers("moments", length=3, lo=0.0, lo_open=True)
    half = torch.tensor(body.numbers("half_extents", length=3, lo=0.0, lo_open=True), dtype=F64)
    com = torch.tensor(body.numbers("centre_of_mass", length=3) if body.has("centre_of_mass") else [0.0] * 3, dtype=F64)
    if bool((com.abs() > half).any()):
        raise ConfigError(
            f"{body.prefix}.centre_of_mass = {com.tolist()} m lies outside the box (each |value| <= half_extents)"
        )
    d = 3
    wall_n, wall_c = planes(cfg.section("walls"), "planes", d)
    n_planes = wall_n.shape[0]
    mu, e = coefficients(cfg, n_planes)
    verts = corners(half)
    V = verts.shape[0]
    kinds = (
        VertexPlanes(
            torch.zeros(V * n_planes, dtype=torch.long),
            verts.repeat(n_planes, 1),
            wall_n.repeat_interleave(V, 0),
            wall_c.repeat_interleave(V, 0),
            torch.arange(n_planes).repeat_interleave(V),
            dc=d,
        ),
    )
    anchors = torch.zeros(0, d, dtype=F64)
    reach = 4.0 * float(half.norm())
    system = System(
        name=cfg.name,
        d=d,
        n_bodies=1,
        points_per_body=4,
        anchors=anchors,
        constraints=make_constraints(4, d, anchors, dist=rigid_body_distances(1, d)),
        detector=Detector(kinds, 4, anchors, d),
        n_slots=n_planes,
        drawing=Drawing(
            radii=half.clone(),
            segments=torch.zeros(0, 2, dtype=torch.long),
            plane_normal=wall_n,
            plane_offset=wall_c,
            shape="box3d",
            view=((-reach, reach), (-reach, reach), (0.0, 2 * reach)),
        ),
    )
    g = cfg.section("potential").number("gravity", 9.81, lo=0.0)
    params = Params(
        Inertia(torch.tensor([mass], dtype=F64), torch.tensor([moments], dtype=F64), com[None]),
        SumPotential(Gravity(g, torch.tensor([0.0, 0.0, 1.0], dtype=F64), 4)),
        mu,
        e,
    )
    init = cfg.section("init")
    size = float(half.max())
    height = _range(init, "height", (4.0 * size, 6.0 * size), lo=0.0)
    speed = _range(init, "speed", (1.0, 1.3), lo=0.0)
    vertical = _range(init, "vertical_speed", (-0.3, 0.2))
    spin = _range(init, "spin", (1.5, 6.5), lo=0.0)
    base = -wall_c[0] * wall_n[0]  # the first plane's point nearest the origin

    def draw(k: int, gen: torch.Generator) -> State:
        def uni(lo_hi):
            return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * torch.rand(k, generator=gen, dtype=F64)

        def direction():
            u = torch.randn(k, 3, generator=gen, dtype=F64)
            return u / u.norm(dim=-1, keepdim=True)

        q = torch.randn(k, 4, generator=gen, dtype=F64)  # uniform on rotations once normalised
        heading = 2 * math.pi * torch.rand(k, generator=gen, dtype=F64)
        s = uni(speed)
        velocity = torch.stack([s * heading.cos(), s * heading.sin(), uni(vertical)], -1)
        position = base + torch.stack([torch.zeros(k, dtype=F64), torch.zeros(k, dtype=F64), uni(height)], -1)
        x, v = pose_to_points(position, q, velocity, uni(spin)[:, None] * direction())
        return State(x, v)

    def sample(count: int, gen: torch.Generator, dtype: torch.dtype) -> State:
        state = rejection_sample(lambda k: draw(k, gen), system.detector.gaps, count, cfg.name)
        return State(state.x.to(dtype), state.v.to(dtype))

    return Task(cfg, system, params, sample)
