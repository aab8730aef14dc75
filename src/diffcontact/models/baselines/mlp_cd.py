"""MLP-CD-CLNN (paper Sec. 5): the learned CLNN between contacts, an MLP for the velocity jump.

Each frame: one RK4 step of the learned constrained Lagrangian dynamics (the Simulator's own ``flow``), then the
task's true collision detection; where any contact candidate is active, Δv = MLP([x, v] flattened) is added to
the velocity instead of the contact model's impulse.  μ and e are not learned.
"""

from __future__ import annotations

import torch

from diffcontact.models.baselines.base import Baseline, mlp
from diffcontact.models.params import LearnedParams
from diffcontact.simulator import Simulator


class MLPCollisionCLNN(Baseline):
    """MLP-CD-CLNN for ``simulator``'s System: ``params`` the CLNN part, ``jump`` the MLP 2D -> hidden^layers -> D
    (ReLU, D = P d)."""

    def __init__(self, simulator: Simulator, params: LearnedParams, dt: float, hidden: int, layers: int, generator):
        super().__init__()
        self.simulator, self.params, self.dt, self.name = simulator, params, dt, "MLP-CD-CLNN"
        D = simulator.system.n_points * simulator.system.d
        self.jump = mlp([2 * D] + [hidden] * layers + [D], generator).to(torch.float64)

    def step(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.params is None:
            raise TypeError(f"{self.name} has no learned CLNN parameters")
        x1, v1 = self.simulator.flow(self.params(), x, v, self.dt)
        with torch.no_grad():
            hit = (self.simulator.system.detector.gaps(x1) < 0).any(dim=1)  # (B,)
        dv = self.jump(torch.cat([x1.flatten(1), v1.flatten(1)], dim=1)).view_as(v1)
        return x1, v1 + hit[:, None, None].to(v1) * dv
