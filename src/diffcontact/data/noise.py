"""Observation noise on stored frames that keeps the holonomic constraints (spec B, "Noise").

Three cases, chosen from the structure of the constraints (never from the system's name):
- no equality constraints (point masses, the rope): i.i.d. N(0, std²) on every position (m) and velocity (m/s);
- a chain from one fixed pivot (the chain pendulum: distance constraints pivot–0, 0–1, …, no joints): the noise
  is added to the absolute link angles (rad) and their rates (rad/s), then mapped back to Cartesian
  coordinates, as in the published code;
- any other constraints (rigid disks, the gyroscope): Cartesian noise, then positions are projected back onto
  Φ(x) = 0 by Gauss–Newton steps (minimum-norm corrections) and velocities onto J_E v = 0. The resulting noise
  is not exactly i.i.d. Gaussian in any coordinates, but its size is std and the constraints hold to 1e-10.
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.constraints import Constraints
from diffcontact.errors import ConfigError, DatasetError
from diffcontact.systems.pendulum import chain_points

_PROJECTION_STEPS = 50
_PROJECTION_TOL = 1e-12


def check_noise(std: float) -> float:
    """Validate a noise standard deviation (finite, >= 0)."""
    try:
        value = float(std)
    except (TypeError, ValueError):
        raise ConfigError(f"noise = {std!r} is not a number") from None
    if not value >= 0.0 or value == float("inf"):
        raise ConfigError(f"noise = {std} is not a finite number >= 0")
    return value


def noise_kind(cons: Constraints) -> str:
    """'free', 'chain' or 'projected' (see the module docstring)."""
    if cons.count == 0:
        return "free"
    P = cons.P
    chain_j = torch.cat([torch.tensor([P]), torch.arange(P - 1)])
    if (
        cons.d == 2
        and cons.n_joint == 0
        and cons.n_dist == P
        and torch.equal(cons.dist_i.cpu(), torch.arange(P))
        and torch.equal(cons.dist_j.cpu(), chain_j)
        and cons.anchors.shape[0] == 1
    ):
        return "chain"
    return "projected"


def add_noise(
    cons: Constraints, x: torch.Tensor, v: torch.Tensor, std: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy copies of positions and velocities x, v (B, P, d) with standard deviation ``std`` (see module doc)."""
    std = check_noise(std)
    if std == 0.0:
        return x.clone(), v.clone()
    kind = noise_kind(cons)
    if kind == "chain":
        return _chain_noise(cons, x, v, std, generator)
    nx = std * torch.randn(x.shape, generator=generator, dtype=torch.float64).to(x)
    nv = std * torch.randn(v.shape, generator=generator, dtype=torch.float64).to(v)
    x1, v1 = x + nx, v + nv
    if kind == "free":
        return x1, v1
    return _project(cons, x1, v1)


def _chain_noise(cons, x, v, std, generator):
    pivot = cons.anchors.to(x)[0]
    prev_x = torch.cat([pivot.expand(x.shape[0], 1, 2), x[:, :-1]], 1)
    prev_v = torch.cat([torch.zeros_like(v[:, :1]), v[:, :-1]], 1)
    link, dlink = x - prev_x, v - prev_v  # (B, n, 2)
    q = torch.atan2(link[..., 0], -link[..., 1])  # from the downward vertical, as in chain_points
    w = (dlink * torch.stack([torch.cos(q), torch.sin(q)], -1)).sum(-1) / cons.dist_len.to(x)
    q = q + std * torch.randn(q.shape, generator=generator, dtype=torch.float64).to(x)
    w = w + std * torch.randn(w.shape, generator=generator, dtype=torch.float64).to(x)
    return chain_points(pivot, cons.dist_len.to(x), q, w)


def _project(cons, x, v):
    B, P, d = x.shape
    for _ in range(_PROJECTION_STEPS):
        phi = cons.phi(x)  # (B, E)
        if float(phi.abs().max()) < _PROJECTION_TOL:
            break
        J = cons.jac(x)  # (B, E, D)
        step = J.transpose(1, 2) @ torch.linalg.solve(J @ J.transpose(1, 2), phi[..., None])
        x = x - step.reshape(B, P, d)
    else:
        raise DatasetError(
            f"noise projection onto the constraints did not converge (|Φ| = {float(phi.abs().max()):.1e})"
        )
    J = cons.jac(x)
    flat = v.reshape(B, P * d, 1)
    flat = flat - J.transpose(1, 2) @ torch.linalg.solve(J @ J.transpose(1, 2), J @ flat)
    return x, flat.reshape(B, P, d)
