"""Known potentials of the benchmark systems. Each is a callable V(x, inertia): (B, P, d), Inertia -> (B,)
(``state.Potential``; the inertia is the Params' own, see ``Params.potential_energy``).

A learned model replaces them by an ``nn.Module`` with the same signature.  Each also gives its force −∇V in
closed form (``ForcePotential.force``), which the dynamics use instead of autograd's gradient (a double backward in
training); a potential without one gets autograd's (:func:`gradient_force`).
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.inertia import centre_weights
from diffcontact.state import ForcePotential, Inertia, with_anchors


def gradient_force(potential, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
    """−∇V(x) (B, P, d) of ``potential`` (V(x, inertia) -> (B,)) by autograd; its graph is kept when gradients are
    enabled outside (training, gradient tests), so the force is differentiable w.r.t. x and V's parameters."""
    outer = torch.is_grad_enabled()
    with torch.enable_grad():
        xg = x if x.requires_grad else x.detach().requires_grad_(True)
        V = potential(xg, inertia)
        if not V.requires_grad:  # a constant potential
            return torch.zeros_like(x)
        (grad,) = torch.autograd.grad(V.sum(), xg, create_graph=outer)
    return -grad


def field_energy(g: torch.Tensor | float, up: torch.Tensor, stride: int, x: torch.Tensor, inertia: Inertia):
    """V = g Σ_b m_b (z_b · up) (B,), z_b each body's centre of mass: on its first point (of ``stride``) without
    ``inertia.com``, else the affine combination of its points that ``com`` gives (``centre_weights``)."""
    height = x @ up.to(x)  # (B, P)
    if inertia.com is None:
        return g * (height[:, ::stride] * inertia.masses.to(x)).sum(-1)
    w = centre_weights(inertia.masses, inertia.com).to(x).flatten()  # (P,)
    return g * (height * w).sum(-1)


def centre_force(g: torch.Tensor | float, up: torch.Tensor, stride: int, x: torch.Tensor, inertia: Inertia):
    """−∇V (B, P, d) of :func:`field_energy`: −g m_b up on each body's centre (its first of ``stride`` points),
    nothing on the other points; with ``inertia.com``, −g w up on each point, w its share of the mass."""
    B, P, d = x.shape
    if inertia.com is not None:
        w = centre_weights(inertia.masses, inertia.com).to(x).reshape(P, 1)
        return (-g * w * up.to(x)).expand(B, -1, -1)
    pull = (-g * inertia.masses.to(x)[:, None] * up.to(x)).expand(B, -1, -1)  # (B, n_bodies, d)
    if stride == 1:
        return pull
    zeros = x.new_zeros(B, P // stride, stride - 1, d)
    return torch.cat([pull[:, :, None], zeros], dim=2).reshape(B, P, d)


class Gravity(ForcePotential):
    """V = g Σ_b m_b (c_b · up): uniform gravity of strength g (m/s²) pulling along −``up``.

    The masses m_b and centres of mass are the Params' inertia's (they may require grad); a body's centre of mass is
    its first point (``stride`` points per body) unless the inertia gives ``com``. Σ (M x) over a body's points
    equals m c, so this is g Σ (M x)_up of the paper.
    """

    def __init__(self, g: float, up: torch.Tensor, stride: int):
        self.g, self.up, self.stride = g, up, stride

    def __call__(self, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
        return field_energy(self.g, self.up, self.stride, x, inertia)

    def force(self, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
        return centre_force(self.g, self.up, self.stride, x, inertia)


class Springs(ForcePotential):
    """V = Σ_s k_s (|x_i − x_j| − l_s)² over spring endpoints (i, j) in extended point indices.

    Indices >= P refer to fixed ``anchors`` (n_anchors, d). There is no ½ factor (as in the benchmark's rope).
    """

    def __init__(self, i: torch.Tensor, j: torch.Tensor, rest: torch.Tensor, k: torch.Tensor, anchors: torch.Tensor):
        self.i, self.j, self.rest, self.k, self.anchors = i, j, rest, k, anchors

    def __call__(self, x: torch.Tensor, inertia: Inertia | None = None) -> torch.Tensor:
        ext = with_anchors(x, self.anchors)
        length = (ext[:, self.i] - ext[:, self.j]).norm(dim=-1)
        return (self.k.to(x) * (length - self.rest.to(x)) ** 2).sum(-1)

    def force(self, x: torch.Tensor, inertia: Inertia | None = None) -> torch.Tensor:
        """−2 k (|x_i − x_j| − l) u on i and its opposite on j, u the unit vector from j to i (none on anchors)."""
        ext = with_anchors(x, self.anchors)
        delta = ext[:, self.i] - ext[:, self.j]  # (B, S, d)
        length = delta.norm(dim=-1, keepdim=True)
        pull = -2 * self.k.to(x)[:, None] * (length - self.rest.to(x)[:, None]) * delta / length
        i, j = self.i.to(x.device), self.j.to(x.device)
        return torch.zeros_like(ext).index_add(1, i, pull).index_add(1, j, -pull)[:, : x.shape[1]]


class SumPotential(ForcePotential):
    """The sum of several potentials (an empty sum is V = 0)."""

    def __init__(self, *terms):
        self.terms = terms

    def __call__(self, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
        total = x.new_zeros(x.shape[0]) + 0.0 * x.flatten(1).sum(-1)  # keeps V connected to x
        for term in self.terms:
            total = total + term(x, inertia)
        return total

    def force(self, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
        """The sum of the terms' forces: each term's closed form, or autograd's gradient of a term without one."""
        total = torch.zeros_like(x)
        for term in self.terms:
            force = term.force(x, inertia) if isinstance(term, ForcePotential) else gradient_force(term, x, inertia)
            total = total + force
        return total
