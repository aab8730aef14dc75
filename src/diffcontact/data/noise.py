"""Observation noise on stored frames that keeps the holonomic constraints (as the published data pipeline adds it).

Three cases, chosen from what the System declares (never from its name):
- a System with ``noise_coordinates`` (the chain pendulum: its absolute link angles in rad and their rates in
  rad/s): i.i.d. N(0, std²) on those coordinates, then mapped back to Cartesian coordinates, as in the published
  code;
- otherwise, no equality constraints (point masses, the rope): i.i.d. N(0, std²) on every position (m) and
  velocity (m/s);
- otherwise (rigid disks, the gyroscope): Cartesian noise, then positions are projected back onto
  Φ(x) = 0 by Gauss–Newton steps (minimum-norm corrections) and velocities onto J_E v = 0. The resulting noise
  is not exactly i.i.d. Gaussian in any coordinates, but its size is std and the constraints hold to 1e-10.
"""

from __future__ import annotations

import torch

from diffcontact.errors import ConfigError, DatasetError
from diffcontact.systems.base import System

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


def noise_kind(system: System) -> str:
    """'free', 'projected' or the name of the System's ``noise_coordinates`` (see the module docstring)."""
    if system.noise_coordinates is not None:
        return system.noise_coordinates.name
    return "free" if system.constraints.count == 0 else "projected"


def add_noise(
    system: System, x: torch.Tensor, v: torch.Tensor, std: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy copies of positions and velocities x, v (B, P, d) of ``system`` with standard deviation ``std`` (see
    the module doc)."""
    std = check_noise(std)
    if std == 0.0:
        return x.clone(), v.clone()
    coords = system.noise_coordinates
    if coords is not None:
        q, w = coords.from_cartesian(x, v)
        q = q + std * torch.randn(q.shape, generator=generator, dtype=torch.float64).to(x)
        w = w + std * torch.randn(w.shape, generator=generator, dtype=torch.float64).to(x)
        return coords.to_cartesian(q, w)
    nx = std * torch.randn(x.shape, generator=generator, dtype=torch.float64).to(x)
    nv = std * torch.randn(v.shape, generator=generator, dtype=torch.float64).to(v)
    x1, v1 = x + nx, v + nv
    if system.constraints.count == 0:
        return x1, v1
    try:
        return system.constraints.project(x1, v1, _PROJECTION_TOL, _PROJECTION_STEPS)
    except FloatingPointError as err:
        raise DatasetError(f"noise {err}") from None
