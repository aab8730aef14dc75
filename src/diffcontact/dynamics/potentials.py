"""Known potentials of the benchmark systems. Each is a callable V(x, masses): (B, P, d), (n_bodies,) -> (B,)
(``state.Potential``; the masses are the Params' own, see ``Params.potential_energy``).

A learned model replaces them by an ``nn.Module`` with the same signature; the dynamics take ∇V by
autograd, so they never need a closed-form gradient.
"""

from __future__ import annotations

import torch

from diffcontact.state import with_anchors


class Gravity:
    """V = g Σ_b m_b (c_b · up): uniform gravity of strength g (m/s²) pulling along −``up``.

    The masses m_b (n_bodies,) are the Params' (they may require grad); the centre of each body is its first
    point (``stride`` points per body). Σ (M x) over a body's points equals m c, so this is g Σ (M x)_up of the
    paper.
    """

    def __init__(self, g: float, up: torch.Tensor, stride: int):
        self.g, self.up, self.stride = g, up, stride

    def __call__(self, x: torch.Tensor, masses: torch.Tensor) -> torch.Tensor:
        height = x[:, :: self.stride] @ self.up.to(x)  # (B, n_bodies)
        return self.g * (height * masses.to(x)).sum(-1)


class Springs:
    """V = Σ_s k_s (|x_i − x_j| − l_s)² over spring endpoints (i, j) in extended point indices.

    Indices >= P refer to fixed ``anchors`` (n_anchors, d). There is no ½ factor (as in the benchmark's rope).
    """

    def __init__(self, i: torch.Tensor, j: torch.Tensor, rest: torch.Tensor, k: torch.Tensor, anchors: torch.Tensor):
        self.i, self.j, self.rest, self.k, self.anchors = i, j, rest, k, anchors

    def __call__(self, x: torch.Tensor, masses: torch.Tensor | None = None) -> torch.Tensor:
        ext = with_anchors(x, self.anchors)
        length = (ext[:, self.i] - ext[:, self.j]).norm(dim=-1)
        return (self.k.to(x) * (length - self.rest.to(x)) ** 2).sum(-1)


class SumPotential:
    """The sum of several potentials (an empty sum is V = 0)."""

    def __init__(self, *terms):
        self.terms = terms

    def __call__(self, x: torch.Tensor, masses: torch.Tensor) -> torch.Tensor:
        total = x.new_zeros(x.shape[0]) + 0.0 * x.flatten(1).sum(-1)  # keeps V connected to x
        for term in self.terms:
            total = total + term(x, masses)
        return total
