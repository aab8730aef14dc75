"""The first states of a split's chunks, learned with the model on data recorded with observation noise.

A chunk is predicted from its first frame, and on noisy data that frame is noisy: on BP5-e at noise 0.05 (half a
ball's radius) chunks start with balls overlapping each other or a wall, and the loss of the true model over the
noisy training chunks is least at e = 0 (0.1154 against 0.1246 at the true e = 1, 100 chunks).  Learning each
chunk's first state with the model, its recorded first frame kept as data (the loss compares the predicted frame 0,
the learned state, with it), removes that bias: the same loss, least over the first states, is 0.0902 at e = 0 and
0.0899 at e = 1 (``tests/test_first_states.py``; docs/training.md, "Noisy data").

Each chunk has a correction (dx, dv) of its recorded first frame, in the coordinates the noise was drawn in: of
every position and velocity (P, d) on free points, of the link angles and rates (k,) on a System with
``noise_coordinates`` (the chain pendulum), whose corrected state is then on the constraints by construction.  There
the bias is the same (CP3-e at noise 0.05: the squared loss of the true model from the recorded frames is least at e
0.95 or below, least over the first states at the true e = 1).  A batch takes its chunks'
corrections as leaves of the graph, and after its backward pass tries a step of each chunk's correction, every entry
moved against its gradient's sign, on the batch's rows alone (a chunk's correction moves only in the steps whose
batch holds it).  The step is kept where it lowers its chunk's loss under the same model, and its size then grows
(×1.2, up to the full step); elsewhere it is not taken and the chunk's step is halved (down to 1/16 of the full
step).  Plain descent does not serve
a chunk with a collision: its loss is piecewise smooth, with a jump where a contact appears or vanishes at a
frame's end, and descent steps cross those jumps.  On the CP3-e data at noise 0.05 with every property true,
RMSprop's (or a sign step's) loss over 400 chunks fell from 0.1105 to 0.095 in 25 steps, then rose to 0.100–0.103
by step 200 (the chunks with a collision from 0.139 to 0.145, the others still falling); with the steps that raised
a chunk's loss not taken, 0.078.  The corrections are buffers of the Lightning module (saved in its checkpoints), not
parameters.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from diffcontact.systems.base import NoiseCoordinates

SHRINK, GROW = 0.5, 1.2  # (a chunk's step after a trial that was not kept, and after one that was)
# (the least step: a chunk whose steps shrank to nothing would stop following the model, which keeps moving; on BP5-e
# at noise 0.05 the corrections froze early and e ended at 0.893 against 0.937 with RMSprop)
MIN_SCALE = 1 / 16


class FirstStates(nn.Module):
    """Corrections (dx, dv) of the first frames of ``n`` chunks: each of ``shape``, (P, d) in m and m/s on free points,
    (k,) in the units of ``coords`` (rad and rad/s for the chain's link angles) where they are given."""

    dx: torch.Tensor
    dv: torch.Tensor
    scale: torch.Tensor
    steps: torch.Tensor

    def __init__(self, n: int, shape: tuple[int, ...], dtype: torch.dtype, coords: NoiseCoordinates | None = None):
        super().__init__()
        self.coords = coords
        self.register_buffer("dx", torch.zeros(n, *shape, dtype=dtype))
        self.register_buffer("dv", torch.zeros(n, *shape, dtype=dtype))
        self.register_buffer("scale", torch.ones(n, dtype=dtype))  # (of the step: halved where one was not taken)
        self.register_buffer("steps", torch.zeros(n, dtype=torch.long))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        # (a checkpoint of the earlier RMSprop rule: its running squares dropped, every chunk's step full)
        if state_dict.pop(prefix + "square", None) is not None and prefix + "scale" not in state_dict:
            state_dict[prefix + "scale"] = torch.ones_like(self.scale)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def take(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrections dx, dv (B, *shape) of chunks ``index`` (B,), as leaves that require gradients."""
        return self.dx[index].clone().requires_grad_(True), self.dv[index].clone().requires_grad_(True)

    @torch.no_grad()
    def update(
        self,
        index: torch.Tensor,
        grad_x: torch.Tensor,
        grad_v: torch.Tensor,
        lr: float,
        losses: torch.Tensor,
        loss_at: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    ) -> torch.Tensor:
        """One step of the corrections of chunks ``index`` (B,), whose losses (B,) at their corrections are ``losses``
        and gradients (B, *shape) ``grad_x``, ``grad_v``: each entry moved by ``lr`` × the chunk's step against its
        gradient's sign, kept where ``loss_at(dx, dv)`` (the chunks' losses (B,) at corrections dx, dv, under the same
        model) is below ``losses``.  Returns which chunks moved (B,) bool."""
        dx, dv = self.dx[index], self.dv[index]
        step = (lr * self.scale[index]).reshape(-1, *[1] * (grad_x.dim() - 1))
        trial_x, trial_v = dx - step * grad_x.sign().to(dx), dv - step * grad_v.sign().to(dv)
        better = loss_at(trial_x, trial_v).detach().to(losses) < losses.detach()
        keep = better.reshape(step.shape)
        self.dx[index], self.dv[index] = torch.where(keep, trial_x, dx), torch.where(keep, trial_v, dv)
        grown = (GROW * self.scale[index]).clamp(max=1.0)
        shrunk = (SHRINK * self.scale[index]).clamp(min=MIN_SCALE)
        self.scale[index] = torch.where(better.to(self.scale.device), grown, shrunk)
        self.steps[index] += 1
        return better

    def start(
        self, x0: torch.Tensor, v0: torch.Tensor, dx: torch.Tensor, dv: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrected first frames x, v (B, P, d) of recorded ones x0, v0 (B, P, d) and corrections dx, dv (B,
        *shape): added to them, or to their coordinates, mapped back (differentiable in the corrections)."""
        if self.coords is None:
            return x0 + dx, v0 + dv
        q, w = self.coords.from_cartesian(x0, v0)
        return self.coords.to_cartesian(q + dx.to(q), w + dv.to(w))

    def corrected(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every chunk x, v (n, L, P, d) of the split with its first frame corrected (no gradient)."""
        with torch.no_grad():
            x0, v0 = self.start(x[:, 0], v[:, 0], self.dx.to(x), self.dv.to(v))
        return torch.cat([x0[:, None], x[:, 1:]], 1), torch.cat([v0[:, None], v[:, 1:]], 1)
