"""The first states of a split's chunks, learned with the model on data recorded with observation noise.

A chunk is predicted from its first frame, and on noisy data that frame is noisy: on BP5-e at noise 0.05 (half a
ball's radius) chunks start with balls overlapping each other or a wall, and the loss of the true model over the
noisy training chunks is least at e = 0 (0.1148 against 0.1237 at the true e = 1).  Learning each chunk's first
state with the model, its recorded first frame kept as data (the loss compares the predicted frame 0, the learned
state, with it), removes that bias: the same loss, least over the first states, is 0.0888 at e = 0 and 0.0835 at
e = 1 (docs/training.md, "Noisy data").

Each chunk has a correction (dx, dv) (P, d) added to its recorded first frame.  A batch takes its chunks'
corrections as leaves of the graph, and after its backward pass moves them by RMSprop on their rows alone (a
running mean of squared gradients per entry, bias-corrected by the chunk's own count of steps), so that a chunk's
correction moves only in the steps whose batch holds it: Adam's momentum, shared by the whole tensor, would move it
in every step.  The corrections are buffers of the Lightning module (saved in its checkpoints), not parameters.
"""

from __future__ import annotations

import torch
from torch import nn

BETA = 0.999  # (the running mean of squared gradients: Adam's β2)
EPS = 1e-12


class FirstStates(nn.Module):
    """Corrections (dx, dv) of the first frames of ``n`` chunks of P points in d dimensions (m, m/s)."""

    dx: torch.Tensor
    dv: torch.Tensor
    square: torch.Tensor
    steps: torch.Tensor

    def __init__(self, n: int, points: int, d: int, dtype: torch.dtype):
        super().__init__()
        self.register_buffer("dx", torch.zeros(n, points, d, dtype=dtype))
        self.register_buffer("dv", torch.zeros(n, points, d, dtype=dtype))
        self.register_buffer("square", torch.zeros(n, 2, points, d, dtype=dtype))  # (of the gradients: dx, dv)
        self.register_buffer("steps", torch.zeros(n, dtype=torch.long))

    def take(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrections dx, dv (B, P, d) of chunks ``index`` (B,), as leaves that require gradients."""
        return self.dx[index].clone().requires_grad_(True), self.dv[index].clone().requires_grad_(True)

    @torch.no_grad()
    def update(self, index: torch.Tensor, grad_x: torch.Tensor, grad_v: torch.Tensor, lr: float) -> None:
        """One RMSprop step of the corrections of chunks ``index`` (B,) along their gradients (B, P, d); ``lr``: the
        largest move of an entry (its first step moves it by ``lr``)."""
        grad = torch.stack([grad_x, grad_v], 1).to(self.square)
        steps = self.steps[index] + 1
        square = BETA * self.square[index] + (1 - BETA) * grad.square()
        unbiased = square / (1 - BETA ** steps.to(square))[:, None, None, None]
        move = lr * grad / (unbiased.sqrt() + EPS)
        self.square[index], self.steps[index] = square, steps
        self.dx[index] -= move[:, 0]
        self.dv[index] -= move[:, 1]

    def corrected(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every chunk x, v (n, L, P, d) of the split with its first frame corrected (no gradient)."""
        with torch.no_grad():
            x0, v0 = x[:, 0] + self.dx.to(x), v[:, 0] + self.dv.to(v)
        return torch.cat([x0[:, None], x[:, 1:]], 1), torch.cat([v0[:, None], v[:, 1:]], 1)
