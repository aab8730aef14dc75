"""The batched State and the Params of a system, kept apart from its static structure (the System).

Shapes: B = batch (trajectories), P = points (bodies × points per body), d = spatial dimension.
Params may hold plain tensors (ground truth) or tensors produced by ``nn.Module``s (learned models): the
physics code only reads them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch

Potential = Callable[[torch.Tensor, "Inertia"], torch.Tensor]
"""A potential energy V(x, inertia): positions (B, P, d) and the bodies' :class:`Inertia` -> (B,), in joules (any
consistent unit).  The inertia is that of the Params holding V (gravity reads its masses and centres of mass; most
terms ignore it), so replacing the inertia never leaves the potential with other masses."""


def with_anchors(x: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """Positions with the fixed ``anchors`` (n_anchors, d) appended, addressed by extended point indices P, P + 1,
    ...: (B, P, d) -> (B, P + n_anchors, d)."""
    return torch.cat([x, anchors.to(x).expand(x.shape[0], -1, -1)], dim=1)


class ForcePotential(ABC):
    """A potential that also gives its force −∇V(x) in closed form, as ordinary differentiable tensor operations.

    The dynamics use :meth:`force` instead of autograd's gradient of V (whose backward is a double backward): the
    same values, a cheaper training step."""

    @abstractmethod
    def force(self, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
        """−∇V(x): positions (B, P, d) in m and the bodies' inertia (as V reads it; the networks ignore it) -> forces
        (B, P, d) in N."""


@dataclass(frozen=True)
class State:
    """Positions ``x`` (B, P, d) and velocities ``v`` (B, P, d) of every point."""

    x: torch.Tensor
    v: torch.Tensor

    @property
    def batch(self) -> int:
        return self.x.shape[0]

    def check_finite(self, where: str = "state") -> State:
        """Raise FloatingPointError naming the first batch element with a NaN/Inf entry."""
        bad = ~(torch.isfinite(self.x).flatten(1).all(1) & torch.isfinite(self.v).flatten(1).all(1))
        if bool(bad.any()):
            idx = int(torch.nonzero(bad)[0])
            raise FloatingPointError(
                f"{where}: non-finite position or velocity in batch element {idx} "
                f"({int(bad.sum())} of {bad.numel()} elements affected)"
            )
        return self


@dataclass(frozen=True)
class Inertia:
    """Masses (n_bodies,) in kg, per-axis second moments per unit mass about the centre of mass (n_bodies, k) in m²,
    and where given the centre of mass ``com`` (n_bodies, k) in m, in the body frame from the body's first point.

    k = 0 for point masses, d for extended bodies (2D body: 3 points, 3D body: 4 points). For a disk of
    radius r the moments are r²/4 per axis. ``com`` None: the centre of mass is the first point (every system but
    the box, whose first point is its geometric centre and whose mass may sit off it).
    """

    masses: torch.Tensor
    moments: torch.Tensor
    com: torch.Tensor | None = None


@dataclass(frozen=True)
class Params:
    """The physical properties a model may learn.

    inertia: :class:`Inertia`; potential: V(x, inertia) -> (B,) (:data:`Potential`, read through
    :meth:`potential_energy`); mu: (n_slots,) friction coefficients >= 0; e: (n_slots,) Poisson coefficients of
    restitution in [0, 1].
    """

    inertia: Inertia
    potential: Potential
    mu: torch.Tensor
    e: torch.Tensor

    def potential_energy(self, x: torch.Tensor) -> torch.Tensor:
        """V(x) (B,) in J at positions x (B, P, d), with this Params' inertia."""
        return self.potential(x, self.inertia)

    def replace(self, **changes) -> Params:
        """A copy with some fields replaced (e.g. ``params.replace(mu=new_mu)``)."""
        return replace(self, **changes)
