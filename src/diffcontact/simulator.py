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

from diffcontact.contact.impulse import ContactModel
from diffcontact.contact.toi import MAX_EVENTS, toi_step
from diffcontact.dynamics.hamiltonian import hamiltonian_field, momentum, velocity
from diffcontact.dynamics.inertia import body_blocks
from diffcontact.dynamics.lagrangian import lagrangian_field
from diffcontact.errors import ConfigError
from diffcontact.integrate import rk4_step
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

    def step(self, state: State, params: Params, dt: float) -> tuple[State, torch.Tensor]:
        """One frame of dt (s): ``substeps`` substeps, each RK4 then contacts (Algorithm 1, or at the time of
        impact). Returns (state at t + dt, in_contact (B,) bool: a contact in any substep)."""
        h = dt / self.substeps
        x, v = state.x, state.v
        hit = torch.zeros(state.batch, dtype=torch.bool)
        for _ in range(self.substeps):
            x, v, sub_hit = self._substep(params, x, v, h)
            hit = hit | sub_hit
        return State(x, v), hit

    def _substep(
        self, params: Params, x: torch.Tensor, v: torch.Tensor, h: float
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        sys = self.system
        if self.time_of_impact:
            flow = partial(self.flow, params)
            return toi_step(flow, self.contact_model, sys.constraints, sys.detector, params, x, v, h, self.max_events)
        x1, v1 = self.flow(params, x, v, h)
        v1, hit = self.contact_model(sys.constraints, sys.detector, params, x1, v1, h)
        return x1, v1, hit

    def rollout(
        self, state: State, params: Params, dt: float, frames: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``frames`` frames starting at ``state`` (frame 0): x, v (B, T, P, d) and in_contact (B, T).

        Raises FloatingPointError naming the frame and batch element if the state becomes non-finite.
        """
        xs, vs = [state.x], [state.v]
        flags = [torch.zeros(state.batch, dtype=torch.bool)]
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
    solver=None,
    on_failure: str = "raise",
    time_of_impact: bool | None = None,
    substeps: int | None = None,
) -> Simulator:
    """The Simulator of a Task: its contact compensation from ``contact.compensation`` (default 1/8); the
    time-stepping scheme from ``contact.time_of_impact`` and ``task.substeps`` unless given here."""
    comp = task.config.section("contact").number("compensation", 0.125, lo=0.0, hi=1.0)
    if reg < 0:
        raise ConfigError(f"reg = {reg:g} is not >= 0")
    model = ContactModel(reg=reg, compensation=comp, solver=solver, on_failure=on_failure)
    return Simulator(task.system, dynamics, model, time_of_impact=time_of_impact, substeps=substeps)


def simulate_task(
    task_name: str, n: int, steps: int | None, seed: int, out: str, gif: str | None = None, dynamics: str = "lagrangian"
) -> dict:
    """Simulate ``n`` trajectories of a task with its true Params (CM, float64) and write ``out`` (.npz).

    The file holds x, v (N, T, P, d), t (T,) in s, energy (N, T) in J, contact (N, T) bool, the task file's
    text (``config``) and ``meta`` (JSON: versions, seed, dt, command arguments). It is written to a temporary
    file and renamed. ``steps`` is the number of frames T (default: the task's ``frames``). Returns meta.
    """
    import json
    import os
    import platform
    import tempfile
    from pathlib import Path

    import numpy as np

    from diffcontact import __version__
    from diffcontact.systems import build_task

    task = build_task(task_name)
    frames = task.frames if steps is None else steps
    if n < 1:
        raise ConfigError(f"n = {n} is not >= 1")
    if frames < 2:
        raise ConfigError(f"steps = {frames} is not >= 2")
    sim = simulator_for(task, dynamics=dynamics)
    state = task.sample(n, seed)
    with torch.no_grad():
        x, v, hit = sim.rollout(state, task.params, task.dt, frames)
        energy = task.system.energy(task.params, x.flatten(0, 1), v.flatten(0, 1)).reshape(n, frames)
    meta = {
        "task": task.config.name,
        "n": n,
        "frames": frames,
        "seed": seed,
        "dt": task.dt,
        "dynamics": dynamics,
        "contact_model": "CM",
        "dtype": task.config.dtype,
        "diffcontact": __version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".npz", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez_compressed(
                fh,
                x=x.numpy(),
                v=v.numpy(),
                t=np.arange(frames) * task.dt,
                energy=energy.numpy(),
                contact=hit.numpy(),
                config=np.array(task.config.source),
                meta=np.array(json.dumps(meta)),
            )
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    if gif:
        from diffcontact.render import render_gif

        render_gif(task.system, x[0].numpy(), hit[0].numpy(), gif, task.dt)
    return meta
