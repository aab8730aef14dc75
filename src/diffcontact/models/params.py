"""Learnable physical parameters (paper Sec. 4 and Suppl. D): inertia, potential, friction and restitution.

Structure stays known (bodies, constraints, contact geometry); the values are learned:
- inertia: masses and per-axis moments per unit mass through exp (positive by construction), 0.1·N(0, 1) init;
  where the task's bodies have a centre of mass off their first point (the box), that offset too, from 0;
- potential: an MLP over all positions (3 hidden layers of 256, Softplus, orthogonal weights), as published;
- μ and e "projected" (the default): the parameter is the value itself, kept in μ ≥ 0 and e ∈ [0, 1] by clamping
  after every optimiser step (``project_``), so that a value on its bound still gets the gradient that brings it
  back (ReLU and hardsigmoid have none there: measured on BD5, a slot whose e reached 0 stayed there, true 0.1);
  initialised μ = 0 (the published U[0, 1) is kept for the transforms below) and e = 0.2 + 0.6·sigmoid(N(0, 1)),
  inside (0, 1).  μ starts at 0 because a slot's loss is flat where its contacts stick: above the truth, a μ that
  sticks every contact the data show sliding gets no gradient back (measured on BP5: slots 13 and 29, true 0.1,
  started near 1 and stayed at 1.0 and 1.76 on that plateau, behind a barrier at μ ≈ 0.5; from 0 the loss falls
  all the way to the truth and both reach it).  Or μ = ReLU(raw) and
  e = hardsigmoid(raw), as published, or the smooth softplus / sigmoid.  One pair for homogeneous tasks (a single
  configured value), one per contact slot otherwise.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, cast

import torch
from torch import nn

from diffcontact.dynamics.potentials import centre_force, field_energy
from diffcontact.errors import ConfigError
from diffcontact.state import ForcePotential, Inertia, Params

if TYPE_CHECKING:
    from diffcontact.systems.base import Links


def _identity(x: torch.Tensor) -> torch.Tensor:
    return x


# the potential: the paper's learned network, that network plus a learned potential of each link's stretch (systems
# with links: the rope), gravity of a learned strength, or the task's own (known, not learned)
POTENTIALS = ("mlp", "linked", "gravity", "known")
MU_TRANSFORMS = {"projected": _identity, "relu": torch.relu, "softplus": nn.functional.softplus}
E_TRANSFORMS = {"projected": _identity, "hardsigmoid": nn.functional.hardsigmoid, "sigmoid": torch.sigmoid}


class MLPPotential(nn.Module, ForcePotential):
    """V(x, inertia): positions (B, P, d) -> (B,); an MLP over the flattened positions with Softplus activations
    (the inertia is not used: the potential is learned in whatever units the learned masses fix).

    Its force −∇V (:meth:`force`) is written out (backpropagation by hand), so that a training step differentiates
    it once instead of through autograd's double backward."""

    def __init__(self, n_inputs: int, hidden: int = 256, layers: int = 3, generator: torch.Generator | None = None):
        super().__init__()
        sizes = [n_inputs] + [hidden] * layers
        mods: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:]):
            mods += [nn.Linear(a, b), nn.Softplus()]
        mods.append(nn.Linear(sizes[-1], 1))
        self.net = nn.Sequential(*mods)
        for m in self.net:
            if isinstance(m, nn.Linear):
                nn.init.orthogonal_(m.weight, generator=generator)
                bound = 1.0 / m.weight.shape[1] ** 0.5  # torch's default bias init, made reproducible
                nn.init.uniform_(m.bias, -bound, bound, generator=generator)

    def forward(self, x: torch.Tensor, inertia: Inertia | None = None) -> torch.Tensor:
        return self.net(x.flatten(1)).squeeze(-1)

    def force(self, x: torch.Tensor, inertia: Inertia | None = None) -> torch.Tensor:
        """−∇V(x) (B, P, d): the layers forward, then their transposes times the Softplus slopes (sigmoids) back.

        Equal to autograd's gradient up to rounding (Softplus' slope above its threshold, 20, is 1 there and the
        sigmoid here, within 2e-9); the output bias and the last activation are not needed."""
        # (Linear, Softplus, ..., Linear), listed: slicing the Sequential would build a new module at every call
        layers = list(self.net)
        linears = cast("list[nn.Linear]", layers[::2])
        if len(linears) == 1:  # (no hidden layer: V is linear)
            return -linears[0].weight.expand(x.shape[0], -1).reshape(x.shape)
        h, slopes = x.flatten(1), []
        for i, lin in enumerate(linears[:-1]):
            z = lin(h)
            slopes.append(torch.sigmoid(z))
            if i < len(linears) - 2:
                h = layers[2 * i + 1](z)
        g = slopes[-1] * linears[-1].weight  # (B, H)
        for lin, slope in zip(reversed(linears[1:-1]), reversed(slopes[:-1])):
            g = (g @ lin.weight) * slope
        return -(g @ linears[0].weight).reshape(x.shape)


class LinkedPotential(nn.Module, ForcePotential):
    """V(x) = MLP(x) + Σ_links φ(s_l): the paper's network over every position (:class:`MLPPotential`) plus one
    small network φ shared by the links, of each link's stretch s = (|x_i − x_j| − rest) / spread (``Links``).

    The second term carries what the first learns slowly: a spring's force changes by its whole size over a stretch
    of a few mm, and the rope's first link pulls toward a fixed anchor (docs/notes/2026-11-28-rope-error-floor.md).
    Its force (:meth:`force`) is written out like the network's."""

    def __init__(
        self, n_inputs: int, links: Links, hidden: int = 256, layers: int = 3, generator: torch.Generator | None = None
    ):
        super().__init__()
        self.body = MLPPotential(n_inputs, hidden, layers, generator=generator)
        self.pair = MLPPotential(1, 64, 2, generator=generator)  # (drawn after the network: its start is the same)
        self.links = links

    def forward(self, x: torch.Tensor, inertia: Inertia | None = None) -> torch.Tensor:
        s, _ = self.links.stretch(x)
        return self.body(x) + self.pair(s.reshape(-1, 1, 1)).reshape(s.shape).sum(-1)

    def force(self, x: torch.Tensor, inertia: Inertia | None = None) -> torch.Tensor:
        """−∇V(x) (B, P, d): the network's, plus −φ'(s) u / spread on each link's point i and its opposite on j."""
        s, u = self.links.stretch(x)
        B, P = x.shape[:2]
        pull = (self.pair.force(s.reshape(-1, 1, 1)).reshape(s.shape) / self.links.spread.to(x))[..., None] * u
        ext = x.new_zeros(B, P + self.links.anchors.shape[0], x.shape[-1])
        ext = ext.index_add(1, self.links.i.to(x.device), pull).index_add(1, self.links.j.to(x.device), -pull)
        return self.body.force(x) + ext[:, :P]


class LearnedGravity(nn.Module, ForcePotential):
    """V = g Σ_b m_b (c_b · up) with a learned strength g = exp(log_g) (m/s²), up the last axis (z in 3-D, y in
    2-D); the centre of each body is its first point (``stride`` points per body).  g starts at 9.81·exp(0.1·N(0, 1)).
    """

    def __init__(self, stride: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64):
        super().__init__()
        start = math.log(9.81) + 0.1 * float(torch.randn((), generator=generator, dtype=dtype))
        self.log_g = nn.Parameter(torch.tensor(start, dtype=dtype))
        self.stride = stride

    @property
    def g(self) -> torch.Tensor:
        return self.log_g.exp()

    def forward(self, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
        return field_energy(self.g, self._up(x), self.stride, x, inertia)

    def force(self, x: torch.Tensor, inertia: Inertia) -> torch.Tensor:
        return centre_force(self.g, self._up(x), self.stride, x, inertia)

    @staticmethod
    def _up(x: torch.Tensor) -> torch.Tensor:
        up = x.new_zeros(x.shape[-1])
        up[-1] = 1.0
        return up


class LearnedParams(nn.Module):
    """Learnable :class:`~diffcontact.state.Params` for a system with ``n_bodies`` bodies.

    n_moments: moments per body (0 for point masses, d for extended bodies); n_points·d: potential input size;
    n_slots: contact slots; homogeneous: one (μ, e) for all slots; potential: one of ``POTENTIALS`` (gravity: along
    the last axis, each body's centre its first of ``points_per_body`` points; known: ``known_potential``, fixed;
    linked: the network plus a potential of each link's stretch, for a system with ``links``); com: learn each
    body's centre of mass (extended bodies whose first point is not it: the box), from the first point.
    ``forward()`` returns Params.
    """

    def __init__(
        self,
        n_bodies: int,
        n_moments: int,
        n_points: int,
        d: int,
        n_slots: int,
        *,
        homogeneous: bool,
        mu_transform: str = "projected",
        e_transform: str = "projected",
        hidden: int = 256,
        layers: int = 3,
        seed: int = 0,
        dtype: torch.dtype = torch.float64,
        potential: str = "mlp",
        points_per_body: int = 1,
        moments_init: float = 1.0,
        known_potential=None,
        links: Links | None = None,
        com: bool = False,
    ):
        super().__init__()
        if potential not in POTENTIALS:
            raise ConfigError(f"potential = {potential!r} is not one of {list(POTENTIALS)}")
        if mu_transform not in MU_TRANSFORMS:
            raise ConfigError(f"mu_transform = {mu_transform!r} is not one of {list(MU_TRANSFORMS)}")
        if e_transform not in E_TRANSFORMS:
            raise ConfigError(f"e_transform = {e_transform!r} is not one of {list(E_TRANSFORMS)}")
        gen = torch.Generator().manual_seed(seed)
        self.n_slots, self.homogeneous = n_slots, homogeneous
        self.mu_transform, self.e_transform = mu_transform, e_transform
        n_coef = 1 if homogeneous else n_slots
        self.log_mass = nn.Parameter(0.1 * torch.randn(n_bodies, generator=gen, dtype=dtype))
        if not (moments_init > 0 and math.isfinite(moments_init)):
            raise ConfigError(f"moments_init = {moments_init!r} is not a finite number > 0 (m² per unit mass)")
        noise = 0.1 * torch.randn(n_bodies, n_moments, generator=gen, dtype=dtype)
        self.log_moments = nn.Parameter(math.log(moments_init) + noise)  # (log 1 = 0: bit for bit the old start)
        # the centre of mass (body frame, from the first point) in units of √moments_init, the radius of gyration the
        # moments start at: Adam moves it about lr of that a step (1e-2 × 3.2 cm = 0.3 mm for the cube)
        self.com_scale = math.sqrt(moments_init)
        self.com_raw = nn.Parameter(torch.zeros(n_bodies, n_moments, dtype=dtype)) if com else None
        mu_raw = torch.rand(n_coef, generator=gen, dtype=dtype)  # (drawn in both cases: the same later draws)
        self.mu_raw = nn.Parameter(torch.zeros_like(mu_raw) if mu_transform == "projected" else mu_raw)
        e_raw = torch.randn(n_coef, generator=gen, dtype=dtype)
        # (projected: in [0.2, 0.8], away from the bounds, where hardsigmoid(N(0, 1)) starts 0.3 % of the slots at 0)
        self.e_raw = nn.Parameter(0.2 + 0.6 * torch.sigmoid(e_raw) if e_transform == "projected" else e_raw)
        if potential == "mlp":
            self.potential = MLPPotential(n_points * d, hidden, layers, generator=gen).to(dtype)
        elif potential == "linked":
            if links is None:
                raise ConfigError('potential = "linked" needs a system with links (the rope); this one has none')
            self.potential = LinkedPotential(n_points * d, links, hidden, layers, generator=gen).to(dtype)
        elif potential == "gravity":
            self.potential = LearnedGravity(points_per_body, generator=gen, dtype=dtype)
        else:
            if known_potential is None:
                raise ConfigError('potential = "known" needs the task\'s potential (known_potential)')
            self.potential = known_potential

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        if self.com_raw is not None and prefix + "com_raw" in missing_keys:  # (a box saved before it learned its
            missing_keys.remove(prefix + "com_raw")  # centre of mass: a uniform box, the start, kept)
            with torch.no_grad():
                self.com_raw.zero_()

    @torch.no_grad()
    def project_(self) -> None:
        """Clamp projected coefficients into their domain (after an optimiser step; no-op for the transforms)."""
        if self.mu_transform == "projected":
            self.mu_raw.clamp_(min=0.0)
        if self.e_transform == "projected":
            self.e_raw.clamp_(0.0, 1.0)

    @property
    def mu(self) -> torch.Tensor:
        """(n_slots,) friction coefficients ≥ 0 (a broadcast view when homogeneous)."""
        return MU_TRANSFORMS[self.mu_transform](self.mu_raw).expand(self.n_slots)

    @property
    def e(self) -> torch.Tensor:
        """(n_slots,) coefficients of restitution in [0, 1]."""
        return E_TRANSFORMS[self.e_transform](self.e_raw).expand(self.n_slots)

    @property
    def inertia(self) -> Inertia:
        com = None if self.com_raw is None else self.com_scale * self.com_raw
        return Inertia(masses=self.log_mass.exp(), moments=self.log_moments.exp(), com=com)

    def forward(self) -> Params:
        return Params(inertia=self.inertia, potential=self.potential, mu=self.mu, e=self.e)
