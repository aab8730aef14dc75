"""The billiards shot (spec G.1): choose the cue ball's initial position and velocity so that the last ball of the
triangle ends at the goal.

θ = (p_x, p_y, v_x, v_y) of the cue ball (m, m/s); the residual is x_last(T) − goal (m), T the task's last frame.
The table is ``configs/tasks/Billiards.toml`` (11 balls, dt 0.003 s, 1024 frames), stepped with the time of impact
(docs/gradients.md): the published end-of-step scheme's gradient w.r.t. the cue state is off by 25–50 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffcontact.errors import ConfigError
from diffcontact.simulator import Simulator, simulator_for
from diffcontact.state import State
from diffcontact.systems.base import Task

TASK = "Billiards"


@dataclass(eq=False)
class Billiards:
    """The shot: the table's Task, its Simulator, the layout at rest (1, n, 2) and the goal (2,) in m."""

    task: Task
    sim: Simulator
    layout: State
    goal: torch.Tensor

    @classmethod
    def build(
        cls,
        balls: int = 11,
        frames: int | None = None,
        cue_position: tuple[float, float] | None = None,
        cue_velocity: tuple[float, float] | None = None,
        goal: tuple[float, float] | None = None,
        time_of_impact: bool = True,
    ) -> Billiards:
        """The table of ``Billiards.toml`` with ``balls`` balls (the cue and a triangle of balls − 1), ``frames``
        frames, and the cue's initial state and the goal replaced where given."""
        from diffcontact.systems.registry import build_task

        if balls < 2:
            raise ConfigError(f"balls = {balls} is not >= 2 (the cue ball and at least one target ball)")
        over: dict[str, dict] = {"bodies": {"masses": [1.0] * balls, "radii": [0.03] * balls}, "init": {}}
        if frames is not None:
            over["task"] = {"frames": frames}
        for key, value in (("cue_position", cue_position), ("cue_velocity", cue_velocity), ("goal", goal)):
            if value is not None:
                over["init"][key] = list(value)
        task = build_task(TASK, overrides=over)
        if task.frames < 2:
            raise ConfigError(f"frames = {task.frames} is not >= 2")
        goal_t = torch.tensor(task.config.section("init").numbers("goal", length=2), dtype=torch.float64)
        return cls(task, simulator_for(task, time_of_impact=time_of_impact), task.sample(1, 0), goal_t)

    @property
    def theta0(self) -> torch.Tensor:
        """The task file's cue state (p_x, p_y, v_x, v_y) (4,)."""
        return torch.cat([self.layout.x[0, 0], self.layout.v[0, 0]])

    def initial_state(self, theta: torch.Tensor) -> tuple[State, torch.Tensor]:
        """The layout with the cue ball (index 0) at θ[:, :2] moving at θ[:, 2:], for θ (B, 4): the State (B, n, 2)
        and feasible (B,) bool, False where the cue ball overlaps another ball."""
        B = theta.shape[0]
        x = torch.cat([theta[:, None, :2], self.layout.x[:, 1:].expand(B, -1, -1)], 1)
        v = torch.cat([theta[:, None, 2:], self.layout.v[:, 1:].expand(B, -1, -1)], 1)
        feasible = (self.task.system.detector.gaps(x.detach()) >= -1e-12).all(1)  # (the triangle's balls touch)
        return State(x, v), feasible

    def rollout(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Positions x (B, T, n, 2) in m, contact flags (B, T) and feasible (B,) of the shots θ (B, 4)."""
        state, feasible = self.initial_state(theta)
        x, _, hit = self.sim.rollout(state, self.task.params, self.task.dt, self.task.frames)
        return x, hit, feasible

    def residual(self, theta: torch.Tensor) -> torch.Tensor:
        """x_last(T) − goal (B, 2) in m for θ (B, 4): the last ball's final position minus the goal; inf where the
        cue ball starts overlapping another ball."""
        x, _, feasible = self.rollout(theta)
        r = x[:, -1, -1] - self.goal
        return torch.where(feasible[:, None], r, torch.full_like(r.detach(), float("inf")))
