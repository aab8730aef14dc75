"""Throwing a disk (the paper's, BD1: m = 0.1 kg, r = 0.1 m, μ = 0.2, e = 0.8, g = 9.81, in the unit box): choose
its initial velocity so that it lands on a target, or its spin so that it rebounds vertically.

The disk starts at rest-angle 0 at (0.25, 0.65) m. A ground bounce is a frame with a contact in which the centre's
v_y goes from < 0 to > 0. Two problems:

- ``hit``: θ = (v_x, v_y, ω) (m/s, m/s, rad/s), from 0; the residual is the centre at the instant of the second
  ground impact minus the target (0.75, 0.1) m. The instant is the root of the ground gap along the flow from the
  frame before the impact (:func:`diffcontact.contact.toi.impact_fraction`), differentiated by the implicit
  function theorem as in the time-of-impact step.
- ``vertical``: (v_x, v_y) = (0.6, 0.4) m/s fixed, θ = (ω,) from 0; the residual is the centre's v_x just after
  the first ground impact (free flight keeps it until the next contact).

The physics is the task's true Params, or the Params learned by a ``diffcontact train`` run (its Simulator with
its learned inertia, potential, μ and e), both stepped with the time of impact (docs/gradients.md).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch

from diffcontact.contact.toi import event_tol, impact_state
from diffcontact.control.optimise import InfeasibleControlError
from diffcontact.errors import ConfigError
from diffcontact.simulator import Simulator, simulator_for
from diffcontact.state import Params, State
from diffcontact.systems.base import Task
from diffcontact.systems.bouncing import disk_points

TASK = "BD1"
START = (0.25, 0.65)
TARGET = (0.75, 0.1)
VERTICAL_VELOCITY = (0.6, 0.4)
MODES = ("hit", "vertical")
MAX_FRAMES = 400


@dataclass(eq=False)
class Physics:
    """What a throw is simulated with: a Task (structure, dt), a Simulator and Params (true or learned)."""

    task: Task
    sim: Simulator
    params: Params
    label: str

    @classmethod
    def true(cls, task: str | Task = TASK) -> Physics:
        """The task's true Params, stepped with the time of impact."""
        from diffcontact.systems.registry import build_task

        task = build_task(task) if isinstance(task, str) else task
        return cls(task, simulator_for(task, time_of_impact=True), task.params, "true properties")

    @classmethod
    def learned(cls, run: str | Path) -> Physics:
        """The Params learned by a ``diffcontact train`` run of a contact model (CM/CMr-CD-CLNN/CHNN), frozen,
        in the run's Simulator switched to the time of impact."""
        from diffcontact.eval.loading import load_run
        from diffcontact.models import ContactModelNet

        loaded = load_run(run)
        net = loaded.net
        if not isinstance(net, ContactModelNet):
            raise ConfigError(f"{run}: model {loaded.model_name!r} learns no physical properties (a baseline)")
        net = net.to(torch.float64).requires_grad_(False)  # (trained in float32 by default; evaluated in float64)
        sim = dataclasses.replace(net.simulator, time_of_impact=True)
        with torch.no_grad():
            params = net.params()
        return cls(loaded.task, sim, params, f"learned properties ({loaded.model_name}, {Path(run).name})")


@dataclass(eq=False)
class Throw:
    """A throw problem (``mode`` in MODES) with its Physics; ``max_frames`` bounds a simulation (frames)."""

    physics: Physics
    mode: str = "hit"
    target: tuple[float, float] = TARGET
    max_frames: int = MAX_FRAMES

    def __post_init__(self):
        if self.mode not in MODES:
            raise ConfigError(f"mode = {self.mode!r} is not one of {list(MODES)}")
        system = self.physics.task.system
        if (system.d, system.n_bodies, system.points_per_body) != (2, 1, 3):
            raise ConfigError(f"task {system.name!r} is not one disk in 2D (the throwing task needs BD1 or alike)")
        up = torch.tensor([0.0, 1.0], dtype=torch.float64)
        normal, offset = system.drawing.plane_normal, system.drawing.plane_offset
        ground = [i for i in range(normal.shape[0]) if torch.equal(normal[i], up) and float(offset[i]) == 0.0]
        if len(ground) != 1:
            raise ConfigError(f"task {system.name!r} has no ground plane y = 0 (walls.lines must include [0, 1, 0])")
        self.ground = ground[0]  # (one disk: its wall contact slots are the walls' indices)

    @property
    def theta0(self) -> torch.Tensor:
        """The initial control: (v_x, v_y, ω) = 0 for ``hit``, ω = 0 for ``vertical``."""
        return torch.zeros(3 if self.mode == "hit" else 1, dtype=torch.float64)

    @property
    def bounces(self) -> int:
        """Ground bounces simulated: 2 (land on the target) or 1 (rebound vertically)."""
        return 2 if self.mode == "hit" else 1

    def initial_state(self, theta: torch.Tensor) -> State:
        """The disks at START, angle 0, with the velocity and spin of θ (B, 3) or (B, 1): x, v (B, 3, 2)."""
        B = theta.shape[0]
        if self.mode == "hit":
            vel, omega = theta[:, :2], theta[:, 2]
        else:
            vel, omega = torch.tensor(VERTICAL_VELOCITY, dtype=theta.dtype).expand(B, 2), theta[:, 0]
        centre = torch.tensor(START, dtype=theta.dtype).expand(B, 1, 2)
        x, v = disk_points(centre, torch.zeros(B, 1, dtype=theta.dtype), vel[:, None], omega[:, None])
        return State(x, v)

    def bounce_frames(
        self, theta: torch.Tensor, bounces: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Simulate the throws θ (B, k) until each has made ``bounces`` ground bounces (default: the mode's) or
        ``max_frames`` frames: x, v (B, T, 3, 2) and the bounce frames (B, bounces), the frame whose step contains
        the impact, −1 where there was none."""
        ph = self.physics
        bounces = self.bounces if bounces is None else bounces
        state = self.initial_state(theta)
        B = theta.shape[0]
        xs, vs = [state.x], [state.v]
        count = torch.zeros(B, dtype=torch.long)
        found = torch.full((B, bounces), -1, dtype=torch.long)
        for t in range(1, self.max_frames):
            new, hit = ph.sim.step(state, ph.params, ph.task.dt)
            new.check_finite(where=f"throw frame {t}")
            up = hit & (state.v[:, 0, 1].detach() < 0) & (new.v[:, 0, 1].detach() > 0)
            count = count + up.long()
            rows = torch.nonzero(up & (count <= bounces)).flatten()
            found[rows, count[rows] - 1] = t
            xs.append(new.x)
            vs.append(new.v)
            state = new
            if bool((found[:, -1] >= 0).all()):
                break
        return torch.stack(xs, 1), torch.stack(vs, 1), found

    def impact_centre(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """The centres (B, 2) in m at the instant, within the next frame, where the disks touch the ground, from
        the states x, v (B, 3, 2) at the start of that frame; the gradient through the impact time by the implicit
        function theorem (as in the time-of-impact step)."""
        ph = self.physics
        flow, rate = partial(ph.sim.flow, ph.params), partial(ph.sim.rate, ph.params)
        B = x.shape[0]
        L = torch.full((B,), ph.task.dt, dtype=x.dtype)
        k = torch.full((B,), self.ground, dtype=torch.long)
        det = ph.task.system.detector
        _, x_imp, _ = impact_state(flow, rate, det, x, v, L, k, torch.full_like(L, 0.5), event_tol(x.dtype))
        return x_imp[:, 0]

    def residual(self, theta: torch.Tensor) -> torch.Tensor:
        """For θ (B, k), ``hit``: the centre at the second ground impact minus the target (B, 2) in m; ``vertical``:
        the centre's v_x after the first ground impact (B, 1) in m/s. Rows of inf where the bounces did not happen
        within max_frames."""
        xs, vs, found = self.bounce_frames(theta)
        ok = found[:, -1] >= 0
        rows = torch.arange(theta.shape[0])
        if self.mode == "hit":
            before = (found[:, -1] - 1).clamp_min(0)
            r = self.impact_centre(xs[rows, before], vs[rows, before]) - torch.tensor(self.target, dtype=theta.dtype)
        else:
            r = vs[rows, found[:, 0].clamp_min(0), 0, :1]
        return torch.where(ok[:, None], r, torch.full_like(r.detach(), float("inf")))

    def landings(self, theta: torch.Tensor, count: int = 2) -> list[list[float]]:
        """The centre (m) at each of the first ``count`` ground impacts of the throw θ (k,) (no gradient);
        InfeasibleControlError if it makes fewer within max_frames."""
        with torch.no_grad():
            xs, vs, found = self.bounce_frames(theta[None], count)
            if bool((found < 0).any()):
                raise InfeasibleControlError(f"the throw θ = {theta.tolist()} makes fewer than {count} bounces")
            before = found[0] - 1
            return self.impact_centre(xs[0, before], vs[0, before]).tolist()

    def trajectory(self, theta: torch.Tensor, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions x (frames, 3, 2) in m and contact flags (frames,) of the throw θ (k,) (no gradient)."""
        ph = self.physics
        with torch.no_grad():
            x, _, hit = ph.sim.rollout(self.initial_state(theta[None]), ph.params, ph.task.dt, frames)
        return x[0], hit[0]
