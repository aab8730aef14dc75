"""The billiards shot (the paper's): choose the cue ball's initial position and velocity so that the last ball of the
triangle ends at the goal.

θ = (p_x, p_y, v_x, v_y) of the cue ball (m, m/s); the residual is x_last(T) − goal (m), T the task's last frame.
The table is ``configs/tasks/Billiards.toml`` (11 balls, dt 0.003 s, 1024 frames), stepped with the time of impact
(docs/gradients.md): the published end-of-step scheme's gradient w.r.t. the cue state is off by 25–50 %.

:meth:`Billiards.search` is the global stage: random cue lines aimed at the triangle, simulated in one batch, each
at its best speed. The table has no walls and no forces, so scaling every velocity by s only rescales time: the
shot (p, s·v) ends where the shot (p, v) is at s·T. One simulation of a shot at the top speed therefore gives the
final position for every slower speed along its line (the last ball's path), hence the speed that brings it
closest to the goal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffcontact.errors import ConfigError
from diffcontact.simulator import Simulator, simulator_for
from diffcontact.state import State
from diffcontact.systems.base import Task

TASK = "Billiards"
CLEARANCE = 0.1  # m: the search's cue balls start this far outside the circle around the triangle


@dataclass
class Search:
    """The global stage's candidates, best first: cue states θ (N, 4) at their best speeds, the last ball's final
    distance to the goal (N,) in m for each (exact by the time scaling, up to rounding), the seed, and the nearest
    distance after each round (one batched simulation each)."""

    thetas: torch.Tensor
    distances: torch.Tensor
    seed: int
    nearest: list[float]


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

    def aim_lines(self, shots: int, generator: torch.Generator, speed: float) -> torch.Tensor:
        """θ (shots, 4) of cue balls at ``speed`` (m/s): the first on the task file's line (θ0's direction), the
        others on random lines: coming from a uniform direction, offset uniformly by up to the radius R of the
        circle around the triangle's balls' centres from the line through its centre, starting R + CLEARANCE (m)
        from it."""
        if shots < 1:
            raise ConfigError(f"shots = {shots} is not >= 1")
        if not speed > 0:
            raise ConfigError(f"speed = {speed!r} is not > 0")
        u = torch.rand(shots - 1, 2, generator=generator, dtype=torch.float64)
        balls = self.layout.x[0, 1:]
        centre = balls.mean(0)
        R = float((balls - centre).norm(dim=1).max())
        phi = 2 * math.pi * u[:, 0]
        d = -torch.stack([phi.cos(), phi.sin()], 1)  # (unit directions of motion, towards the centre)
        start = centre - (R + CLEARANCE) * d + (2 * u[:, 1:] - 1) * R * _normal(d)
        th0 = self.theta0
        v0 = th0[2:] / th0[2:].norm() * speed
        return torch.cat([torch.cat([th0[:2], v0])[None], torch.cat([start, speed * d], 1)])

    def best_speeds(self, lines: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The shots ``lines`` θ (B, 4) simulated in one batch (no gradient), each at its best speed: the factor
        s in (0, 1] of its velocity for which the last ball's path x_last(t) passes closest to the goal at t = s·T
        (linear between frames), since (p, s·v) ends where (p, v) is at s·T. Returns the shots at their best speeds
        (B, 4) and the last ball's final distance to the goal for each (B,) in m (inf where the start is infeasible
        or the last ball never moves)."""
        with torch.no_grad():
            x, _, feasible = self.rollout(lines)
        path = x[:, :, -1]  # (B, T, 2)
        seg = path[:, 1:] - path[:, :-1]
        to_goal = self.goal - path[:, :-1]
        u = ((to_goal * seg).sum(-1) / (seg * seg).sum(-1).clamp_min(1e-300)).clamp(0, 1)  # (B, T - 1)
        dist = (to_goal - u[..., None] * seg).norm(dim=-1)
        best = dist.argmin(1)
        rows = torch.arange(len(lines))
        s = (best + u[rows, best]) / (path.shape[1] - 1)
        distance = torch.where(feasible & (s > 0), dist[rows, best], torch.full_like(s, float("inf")))
        return torch.cat([lines[:, :2], s[:, None] * lines[:, 2:]], 1), distance

    def search(
        self, shots: int, seed: int = 0, speed: float = 1.5, rounds: int = 3, elites: int = 16, spread: float = 0.05
    ) -> Search:
        """The global stage: ``rounds`` simulations of ``shots`` cue lines each, in one batch each, every shot at its
        best speed (:meth:`best_speeds`). Round 1: the lines of :meth:`aim_lines` at ``speed`` (m/s); each later
        round: the ``elites`` nearest lines so far, each rotated by N(0, σ²) rad and shifted across by N(0, (σ/5)²)
        m into shots/elites new ones, σ = ``spread``/4^(round − 2). Returns every shot of finite distance, nearest
        first."""
        if rounds < 1 or elites < 1:
            raise ConfigError(f"rounds = {rounds} and elites = {elites} are not both >= 1")
        g = torch.Generator().manual_seed(seed)
        lines = self.aim_lines(shots, g, speed)
        thetas, distances = self.best_speeds(lines)
        nearest = [float(distances.min())]
        for k in range(1, rounds):
            top = lines[torch.argsort(distances)[: min(elites, len(lines))]]
            parent = top.repeat_interleave(-(-shots // len(top)), 0)[:shots]
            sigma = spread / 4 ** (k - 1)
            turn = sigma * torch.randn(shots, generator=g, dtype=torch.float64)
            shift = sigma / 5 * torch.randn(shots, 1, generator=g, dtype=torch.float64)
            c, s = turn.cos()[:, None], turn.sin()[:, None]
            v = parent[:, 2:]
            v = torch.cat([c * v[:, :1] - s * v[:, 1:], s * v[:, :1] + c * v[:, 1:]], 1)
            new = torch.cat([parent[:, :2] + shift * _normal(v / v.norm(dim=1, keepdim=True)), v], 1)
            new_thetas, new_distances = self.best_speeds(new)
            lines = torch.cat([lines, new])
            thetas, distances = torch.cat([thetas, new_thetas]), torch.cat([distances, new_distances])
            nearest.append(float(distances.min()))
        order = torch.argsort(distances)
        order = order[torch.isfinite(distances[order])]
        return Search(thetas[order], distances[order], seed, nearest)


def _normal(d: torch.Tensor) -> torch.Tensor:
    """The unit directions d (B, 2) turned by +90°."""
    return torch.stack([-d[:, 1], d[:, 0]], 1)
