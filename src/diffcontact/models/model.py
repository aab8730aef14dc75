"""The four models of the paper: the Simulator of a task with learnable Params.

CM-CD-CLNN / CM-CD-CHNN use the exact contact model, CMr-CD-CLNN / CMr-CD-CHNN the regularised one (A + 0.01 I);
CLNN integrates the constrained Lagrangian dynamics in (x, v), CHNN the constrained Hamiltonian dynamics in (x, p).
The structure (bodies, constraints, contact candidates and geometry, dt, integrator) is the task's own: the
ground truth and the model are the same code.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from diffcontact.errors import ConfigError
from diffcontact.models.params import LearnedParams
from diffcontact.simulator import Simulator, simulator_for
from diffcontact.solver.contact_solver import ContactSolver
from diffcontact.state import Params, State

if TYPE_CHECKING:
    from diffcontact.models.baselines import Baseline

CMR_REG = 0.01
MODEL_NAMES = {
    "CM-CD-CLNN": ("lagrangian", 0.0),
    "CM-CD-CHNN": ("hamiltonian", 0.0),
    "CMr-CD-CLNN": ("lagrangian", CMR_REG),
    "CMr-CD-CHNN": ("hamiltonian", CMR_REG),
}


class ContactModelNet(nn.Module):
    """A learnable simulator: ``forward(x0, v0, frames)`` -> predicted x, v (B, frames, P, d) from frame 0."""

    def __init__(self, simulator: Simulator, params: LearnedParams | KnownParams, dt: float, name: str):
        super().__init__()
        self.simulator, self.params, self.dt, self.name = simulator, params, dt, name

    def forward(self, x0: torch.Tensor, v0: torch.Tensor, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
        xs, vs, _ = self.simulator.rollout(State(x0, v0), self.params(), self.dt, frames)
        return xs, vs


class KnownParams(nn.Module):
    """Params that are not learned (a task's true or nominal values) behind the LearnedParams interface."""

    def __init__(self, params: Params):
        super().__init__()
        self.known = params

    def forward(self) -> Params:
        return self.known


def known_model(task, dynamics: str = "lagrangian") -> ContactModelNet:
    """The task's simulator with its own (true or nominal) Params, as a model: ``forward(x0, v0, frames)``."""
    return ContactModelNet(simulator_for(task, dynamics), KnownParams(task.params), task.dt, "nominal")


def build_model(
    task,
    name: str = "CM-CD-CLNN",
    *,
    mu_transform: str = "projected",
    e_transform: str = "projected",
    hidden: int = 256,
    layers: int = 3,
    seed: int = 0,
    solver: ContactSolver | None = None,
    reg: float | None = None,
    potential: str = "mlp",
    moments_init: float = 1.0,
) -> ContactModelNet | Baseline:
    """One of :data:`MODEL_NAMES` for a Task (from :func:`diffcontact.build_task`), float64 parameters; or one of the
    baselines' ``BASELINE_NAMES`` (:func:`diffcontact.models.baselines.build_baseline`: hidden, layers, seed apply).

    ``solver`` (a :class:`~diffcontact.solver.ContactSolver`; default: one that raises on failure) solves the
    contact problems, e.g. ``ContactSolver(on_failure="count")`` to continue and count failures.  ``reg``
    replaces a CMr model's regularisation of the effective mass (A + reg·I, 1/kg; default ``CMR_REG``, the
    paper's).  ``potential``: "mlp" (the paper's learned network), "linked" (that network plus a learned potential of
    each link's stretch, for a system with links: the rope), "gravity" (uniform gravity along −z, −y in 2-D, of a
    learned strength g) or "known" (the task's own, not learned); ``moments_init``: the scale (m² per unit
    mass) around which the learned second moments start (about the square of the bodies' size; the baselines' too).
    A task whose bodies have a centre of mass off their first point (``Inertia.com``: the box) has it learned, from
    that point, by every model that learns an inertia.
    """
    from diffcontact.models.baselines import BASELINE_NAMES, build_baseline

    if name in BASELINE_NAMES:  # (the paper's baselines: same interface, see models/baselines)
        if potential != "mlp":
            raise ConfigError(f"potential = {potential!r} is for the contact models; {name} learns its own network")
        if reg is not None:
            raise ConfigError(f"reg = {reg:g} is for the regularised models (CMr-...), not {name}")
        return build_baseline(task, name, hidden=hidden, layers=layers, seed=seed, moments_init=moments_init)
    if name not in MODEL_NAMES:
        raise ConfigError(f"model = {name!r} is not one of {list(MODEL_NAMES) + list(BASELINE_NAMES)}")
    dynamics, default_reg = MODEL_NAMES[name]
    if reg is not None and not default_reg:
        raise ConfigError(f"reg = {reg:g} is for the regularised models (CMr-...), not {name}")
    if reg is not None and not reg > 0:
        raise ConfigError(f"reg = {reg:g} is not > 0 (the exact model is CM-...)")
    reg = default_reg if reg is None else reg
    system = task.system
    sim = simulator_for(task, dynamics, reg, solver)
    homogeneous = len(task.config.section("contact").numbers("mu")) == 1
    params = LearnedParams(
        system.n_bodies,
        task.params.inertia.moments.shape[-1],
        system.n_points,
        system.d,
        system.n_slots,
        homogeneous=homogeneous,
        mu_transform=mu_transform,
        e_transform=e_transform,
        hidden=hidden,
        layers=layers,
        seed=seed,
        potential=potential,
        points_per_body=system.points_per_body,
        moments_init=moments_init,
        known_potential=task.params.potential if potential == "known" else None,
        links=system.links,
        com=task.params.inertia.com is not None,  # (the box: its centre of mass, learned from its centre)
    )
    return ContactModelNet(sim, params, task.dt, name)
