"""Time stepping (paper Algorithm 1): one RK4 step (3/8 rule) of the constrained dynamics, then contacts."""

from __future__ import annotations

from collections.abc import Callable

import torch

Field = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def rk4_step(
    field: Field, x: torch.Tensor, y: torch.Tensor, dt: float | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One explicit RK4 step, 3/8 rule (stages at 0, 1/3, 2/3, 1; weights (1, 3, 3, 1)/8).

    field(x, y) -> (ẋ, ẏ) for a state (x, y), y = v (Lagrangian) or p (Hamiltonian); dt in s (a float, or a tensor
    that broadcasts against x and y).
    """
    k1x, k1y = field(x, y)
    k2x, k2y = field(x + dt * k1x / 3, y + dt * k1y / 3)
    k3x, k3y = field(x + dt * (k2x - k1x / 3), y + dt * (k2y - k1y / 3))
    k4x, k4y = field(x + dt * (k1x - k2x + k3x), y + dt * (k1y - k2y + k3y))
    return (x + dt * (k1x + 3 * (k2x + k3x) + k4x) / 8, y + dt * (k1y + 3 * (k2y + k3y) + k4y) / 8)
