"""The Simulator: one physics path (Algorithm 1) for ground truth and learned models alike.

Simulator(system, dynamics, contact_model).step / .rollout take a State and Params; Params may be true
values or the output of learnable modules. A frame of length dt runs ``substeps`` substeps of dt/substeps;
each resolves its contacts at the end of the substep (the published scheme) or, with ``time_of_impact``, at
their time of impact inside it (:mod:`diffcontact.contact.toi`). Both default to the System's ``stepping``
(from the task file).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import torch

from diffcontact.contact.impulse import COMPENSATION, ContactModel
from diffcontact.contact.toi import MAX_EVENTS, toi_step
from diffcontact.dynamics.hamiltonian import hamiltonian_field, momentum, velocity
from diffcontact.dynamics.inertia import apply_blocks, body_blocks
from diffcontact.dynamics.lagrangian import lagrangian_field
from diffcontact.errors import ConfigError
from diffcontact.integrate import rk4_step
from diffcontact.solver.contact_solver import ContactSolver
from diffcontact.state import Params, State
from diffcontact.systems.base import System

DYNAMICS = ("lagrangian", "hamiltonian")


@dataclass(eq=False)
class Simulator:
    """Constrained Lagrangian (x, v) or Hamiltonian (x, p) dynamics + a contact model, for one System.

    ``time_of_impact`` and ``substeps`` (None: the System's ``stepping``) choose the time-stepping scheme;
    ``max_events`` bounds the impacts resolved at their time of impact per substep.
    """

    system: System
    dynamics: str = "lagrangian"
    contact_model: ContactModel = field(default_factory=ContactModel)
    time_of_impact: bool | None = None
    substeps: int | None = None
    max_events: int = MAX_EVENTS

    def __post_init__(self):
        if self.dynamics not in DYNAMICS:
            raise ConfigError(f"dynamics = {self.dynamics!r} is not one of {list(DYNAMICS)}")
        if self.time_of_impact is None:
            self.time_of_impact = self.system.stepping.time_of_impact
        if self.substeps is None:
            self.substeps = self.system.stepping.substeps
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, int) or self.substeps < 1:
            raise ConfigError(f"substeps = {self.substeps!r} is not an integer >= 1")
        if self.max_events < 1:
            raise ConfigError(f"max_events = {self.max_events!r} is not >= 1")

    def flow(
        self, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float | torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The smooth part: one RK4 step (no contacts) from (x, v), returning (x, v) at t + dt.

        dt: a float or a tensor (B, 1, 1) in s (a step length per batch element, for the time of impact)."""
        cons = self.system.constraints
        _, Minv = body_blocks(params.inertia)  # (once for the four stages)
        if self.dynamics == "lagrangian":
            return rk4_step(partial(lagrangian_field, cons, params, Minv=Minv), x, v, dt)
        x1, p1 = rk4_step(partial(hamiltonian_field, cons, params, Minv=Minv), x, momentum(params, v), dt)
        return x1, velocity(params, p1)

    def rate(self, params: Params, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The vector field that :meth:`flow` integrates, in velocities: (ẋ, v̇) at (x, v), each (B, P, d)."""
        cons = self.system.constraints
        _, Minv = body_blocks(params.inertia)
        if self.dynamics == "lagrangian":
            return lagrangian_field(cons, params, x, v, Minv=Minv)
        xdot, pdot = hamiltonian_field(cons, params, x, momentum(params, v), Minv=Minv)
        return xdot, apply_blocks(Minv, pdot)

    def step(self, state: State, params: Params, dt: float) -> tuple[State, torch.Tensor]:
        """One frame of dt (s): ``substeps`` substeps, each RK4 then contacts (Algorithm 1, or at the time of
        impact). Returns (state at t + dt, in_contact (B,) bool: a contact in any substep)."""
        substeps = self.substeps
        if substeps is None:  # (unreachable: __post_init__ sets it)
            raise ConfigError("substeps is not set")
        h = dt / substeps
        x, v = state.x, state.v
        hit = torch.zeros(state.batch, dtype=torch.bool, device=state.x.device)
        for _ in range(substeps):
            x, v, sub_hit = self._substep(params, x, v, h)
            hit = hit | sub_hit
        return State(x, v), hit

    def _substep(
        self, params: Params, x: torch.Tensor, v: torch.Tensor, h: float
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        sys = self.system
        if self.time_of_impact:
            flow, rate = partial(self.flow, params), partial(self.rate, params)
            return toi_step(flow, rate, self.contact_model, sys, params, x, v, h, self.max_events)
        x1, v1 = self.flow(params, x, v, h)
        v1, hit = self.contact_model(sys, params, x1, v1, h)
        return x1, v1, hit

    def rollout(
        self, state: State, params: Params, dt: float, frames: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``frames`` frames starting at ``state`` (frame 0): x, v (B, T, P, d) and in_contact (B, T).

        Raises FloatingPointError naming the frame and batch element if the state is or becomes non-finite, and
        ConfigError unless frames >= 2 and dt > 0 (finite).
        """
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 2:
            raise ConfigError(f"frames = {frames!r} is not an integer >= 2 (frame 0 is the initial state)")
        if not 0 < float(dt) < float("inf"):
            raise ConfigError(f"dt = {dt!r} is not a finite time step > 0 (s)")
        state.check_finite(where=f"{self.system.name} initial state")
        if state.batch == 0:  # (an empty batch: nothing to step)
            empty = (state.x.new_zeros(0, frames, *state.x.shape[1:]), state.v.new_zeros(0, frames, *state.v.shape[1:]))
            return (*empty, torch.zeros(0, frames, dtype=torch.bool, device=state.x.device))
        xs, vs = [state.x], [state.v]
        flags = [torch.zeros(state.batch, dtype=torch.bool, device=state.x.device)]
        for t in range(1, frames):
            state, hit = self.step(state, params, dt)
            state.check_finite(where=f"{self.system.name} frame {t}")
            xs.append(state.x)
            vs.append(state.v)
            flags.append(hit)
        return torch.stack(xs, 1), torch.stack(vs, 1), torch.stack(flags, 1)


def simulator_for(
    task,
    dynamics: str = "lagrangian",
    reg: float = 0.0,
    solver: ContactSolver | None = None,
    time_of_impact: bool | None = None,
    substeps: int | None = None,
) -> Simulator:
    """The Simulator of a Task (ground truth and learned models alike): its contact model (CM, or CMr with
    ``reg`` > 0 in 1/kg) with the compensation ``contact.compensation`` (default ``COMPENSATION``) and ``solver``
    (default: a :class:`ContactSolver` that raises on failure); the time-stepping scheme from
    ``contact.time_of_impact`` and ``task.substeps`` unless given here."""
    comp = task.config.section("contact").number("compensation", COMPENSATION, lo=0.0, hi=1.0)
    if reg < 0:
        raise ConfigError(f"reg = {reg:g} is not >= 0")
    lift = task.config.section("contact").choice(
        "compensation_lift", ("pseudo-inverse", "effective-mass"), "pseudo-inverse"
    )
    model = ContactModel(reg=reg, compensation=comp, solver=solver or ContactSolver(), lift=lift)
    return Simulator(task.system, dynamics, model, time_of_impact=time_of_impact, substeps=substeps)
