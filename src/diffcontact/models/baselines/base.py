"""What the three baselines share: an autoregressive rollout of a one-step map, and seeded MLPs."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from diffcontact.state import State

if TYPE_CHECKING:
    from diffcontact.models.params import LearnedParams


def mlp(sizes: list[int], generator: torch.Generator, activation: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """Linear layers of ``sizes`` with ``activation`` between them (none after the last), orthogonal weights and
    torch's default uniform biases, drawn from ``generator`` (reproducible)."""
    mods: list[nn.Module] = []
    for k, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        lin = nn.Linear(a, b)
        nn.init.orthogonal_(lin.weight, generator=generator)
        bound = 1.0 / a**0.5
        nn.init.uniform_(lin.bias, -bound, bound, generator=generator)
        mods.append(lin)
        if k < len(sizes) - 2:
            mods.append(activation())
    return nn.Sequential(*mods)


def point_inverse_inertia(masses: torch.Tensor, moments: torch.Tensor) -> torch.Tensor:
    """Inverse inertia of every point (P,): 1/m for a body's first point, 1/(m μ_k) for its axis point k.

    masses (n_bodies,) in kg, moments (n_bodies, k) in m² per unit mass (k = 0 for point masses).
    """
    per = torch.cat([masses[:, None], masses[:, None] * moments], dim=-1)  # (n, k + 1)
    return (1.0 / per).flatten()


class Baseline(nn.Module):
    """A learned one-step map rolled out autoregressively: ``forward(x0, v0, frames)`` -> x, v (B, frames, P, d)
    from frame 0, the interface of :class:`~diffcontact.models.ContactModelNet`.

    Subclasses define :meth:`step`; ``params`` is the learned CLNN part (:class:`LearnedParams` without contact
    slots) or None.  A non-finite state raises FloatingPointError naming the frame, as the Simulator does.
    """

    name: str
    dt: float
    params: LearnedParams | None

    def step(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One frame: (x, v) (B, P, d) at t -> at t + dt."""
        raise NotImplementedError

    def forward(self, x0: torch.Tensor, v0: torch.Tensor, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
        xs, vs = [x0], [v0]
        x, v = x0, v0
        for t in range(1, frames):
            x, v = self.step(x, v)
            State(x, v).check_finite(where=f"{self.name} frame {t}")
            xs.append(x)
            vs.append(v)
        return torch.stack(xs, 1), torch.stack(vs, 1)
