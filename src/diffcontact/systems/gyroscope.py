"""Gyroscope with a wall (the paper's task): one 3D extended body (4 points) on a ball joint at the origin.

The body's centre of mass is at body-frame offset ``com`` from the joint; its collision shape is a disk of
radius ``disk_radius`` in the e1–e2 plane at height ``disk_height`` along e3 from the centre of mass. The
rim's lowest point against each plane is found in closed form (DiskRimPlanes), one slot per plane.
"""

from __future__ import annotations

import torch

from diffcontact.config import TaskConfig
from diffcontact.contact.detect import Detector
from diffcontact.contact.kinds import DiskRimPlanes
from diffcontact.dynamics.potentials import Gravity, SumPotential
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
from diffcontact.systems.poses import hat


def euler_zxz(phi: torch.Tensor, theta: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (B, 3, 3) of intrinsic ZXZ Euler angles: R = R_z(φ) R_x(θ) R_z(ψ)."""

    def rz(a):
        c, s, z, o = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
        return torch.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(*a.shape, 3, 3)

    def rx(a):
        c, s, z, o = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
        return torch.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(*a.shape, 3, 3)

    return rz(phi) @ rx(theta) @ rz(psi)


TABLES = {
    "body": ("mass", "moments", "com", "disk_radius", "disk_height"),
    "walls": ("planes",),
    "potential": ("gravity",),
    "init": ("angle_max", "precession_rate_max", "nutation_rate_max", "spin_mean", "spin_std"),
}


def build_gyroscope(cfg: TaskConfig) -> Task:
    """Gyroscope from ``[body]`` (mass, moments, com, disk_radius, disk_height), ``[walls]``, ``[potential]``."""
    body = cfg.section("body")
    mass = body.number("mass", lo=0.0, lo_open=True)
    moments = body.numbers("moments", length=3, lo=0.0, lo_open=True)
    com = torch.tensor(body.numbers("com", length=3), dtype=F64)
    radius = body.number("disk_radius", lo=0.0, lo_open=True)
    height = body.number("disk_height", 0.0)
    d = 3
    wall_n, wall_c = planes(cfg.section("walls"), "planes", d)
    n_slots = wall_n.shape[0]
    mu, e = coefficients(cfg, n_slots)
    anchors = torch.zeros(1, d, dtype=F64)
    joint_b = -com  # body-frame point of the joint
    joints = (torch.arange(4)[None], torch.cat([1.0 - joint_b.sum()[None], joint_b])[None], anchors.clone())
    kinds = (
        DiskRimPlanes(
            torch.zeros(n_slots, dtype=torch.long),
            wall_n,
            wall_c,
            torch.full((n_slots,), radius, dtype=F64),
            torch.full((n_slots,), height, dtype=F64),
            torch.arange(n_slots),
            dc=d,
        ),
    )
    reach = float(com.norm()) + radius
    system = System(
        name=cfg.name,
        d=d,
        n_bodies=1,
        points_per_body=4,
        anchors=anchors,
        constraints=make_constraints(4, d, anchors, dist=rigid_body_distances(1, d), joints=joints),
        detector=Detector(kinds, 4, anchors, d),
        n_slots=n_slots,
        drawing=Drawing(
            radii=torch.tensor([radius], dtype=F64),
            segments=torch.tensor([[4, 0]]),
            plane_normal=wall_n,
            plane_offset=wall_c,
            shape="disk3d",
            view=((-reach, reach), (-reach, reach), (-reach, reach)),
        ),
    )
    g = cfg.section("potential").number("gravity", 9.81, lo=0.0)
    m = torch.tensor([mass], dtype=F64)
    params = Params(
        Inertia(m, torch.tensor([moments], dtype=F64)),
        SumPotential(Gravity(g, torch.tensor([0.0, 0.0, 1.0], dtype=F64), 4)),
        mu,
        e,
    )
    init = cfg.section("init")
    a_max = init.number("angle_max", 1.5, lo=0.0)
    phidot_max = init.number("precession_rate_max", 4.5, lo=0.0)
    thetadot_max = init.number("nutation_rate_max", 0.3, lo=0.0)
    spin_mean = init.number("spin_mean", 10.5, lo=0.0)
    spin_std = init.number("spin_std", 1.5, lo=0.0)

    def draw(k: int, gen: torch.Generator) -> State:
        def uni(lo, hi):
            return lo + (hi - lo) * torch.rand(k, generator=gen, dtype=F64)

        phi, theta, psi = uni(-a_max, a_max), uni(-a_max, a_max), uni(-a_max, a_max)
        dphi, dtheta = uni(-phidot_max, phidot_max), uni(-thetadot_max, thetadot_max)
        sign = torch.where(torch.rand(k, generator=gen, dtype=F64) < 0.5, -1.0, 1.0)
        dpsi = sign * (spin_mean + spin_std * torch.randn(k, generator=gen, dtype=F64))
        return State(*gyro_points(com, phi, theta, psi, dphi, dtheta, dpsi))

    def sample(count: int, gen: torch.Generator, dtype: torch.dtype) -> State:
        state = rejection_sample(lambda k: draw(k, gen), system.detector.gaps, count, cfg.name)
        return State(state.x.to(dtype), state.v.to(dtype))

    return Task(cfg, system, params, sample)


def gyro_points(com: torch.Tensor, phi, theta, psi, dphi, dtheta, dpsi) -> tuple[torch.Tensor, torch.Tensor]:
    """Points (B, 4, 3) and velocities of a top on a joint at the origin from ZXZ angles and their rates.

    Body rates ω = E (φ̇, θ̇, ψ̇) with E rows [sθ sψ, cψ, 0], [sθ cψ, −sψ, 0], [cθ, 0, 1]; Ṙ = R [ω]×. The
    centre of mass is R com (the joint, body point −com, sits at the origin); the axis points are com + R_k.
    """
    R = euler_zxz(phi, theta, psi)
    st, ct, sp, cp = torch.sin(theta), torch.cos(theta), torch.sin(psi), torch.cos(psi)
    w = torch.stack([st * sp * dphi + cp * dtheta, st * cp * dphi - sp * dtheta, ct * dphi + dpsi], -1)
    Rdot = R @ hat(w)
    c = R @ com.to(R)
    dc = Rdot @ com.to(R)
    x = torch.cat([c[:, None], c[:, None] + R.mT], dim=1)
    v = torch.cat([dc[:, None], dc[:, None] + Rdot.mT], dim=1)
    return x, v
