"""Learned first states of noisy chunks (train/first_states.py): the update touches only a batch's chunks, by
RMSprop; and on BP5-e at noise 0.05 the loss least over the first states prefers the true e where the loss from
the recorded first frames prefers e = 0."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from diffcontact.data.generate import make_split
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems.registry import build_task
from diffcontact.train.first_states import BETA, FirstStates
from diffcontact.train.module import ContactLightningModule


def test_a_step_moves_only_the_chunks_of_the_batch_by_rmsprop():
    states = FirstStates(5, 2, 3, torch.float64)
    index = torch.tensor([1, 3])
    gx, gv = torch.randn(2, 2, 3, dtype=torch.float64), torch.randn(2, 2, 3, dtype=torch.float64)
    states.update(index, gx, gv, lr=0.01)
    # the first step of RMSprop with bias correction moves every entry by lr against its gradient's sign
    assert torch.allclose(states.dx[index], -0.01 * gx.sign()) and torch.allclose(states.dv[index], -0.01 * gv.sign())
    untouched = torch.tensor([0, 2, 4])
    assert states.dx[untouched].abs().max() == 0 and states.steps.tolist() == [0, 1, 0, 1, 0]
    # a second step of chunk 3 alone: the running mean of squares, bias-corrected by the chunk's own two steps
    before, g2 = states.dx[3].clone(), 2 * gx[1:]
    square = BETA * (1 - BETA) * gx[1].square() + (1 - BETA) * g2[0].square()
    states.update(torch.tensor([3]), g2, torch.zeros_like(g2), lr=0.01)
    expected = before - 0.01 * g2[0] / (square / (1 - BETA**2)).sqrt()
    assert torch.allclose(states.dx[3], expected) and states.steps.tolist() == [0, 1, 0, 2, 0]
    assert torch.allclose(states.dx[1], -0.01 * gx[0].sign())  # (chunk 1 not in the batch: unchanged)
    # the leaves a batch takes
    dx, dv = states.take(index)
    assert dx.requires_grad and torch.equal(dx.detach(), states.dx[index])


@pytest.mark.parametrize("task_name", ["BP5-e", "CP3", "Gyro"])
def test_the_chunks_as_fitted_start_from_their_corrected_first_frames_on_the_constraints(task_name):
    # free points: the recorded first frame plus the correction; a constrained system (the chain pendulum's
    # distance constraints, the gyroscope's rigid body on its pivot): that, projected back onto the constraints
    module = ContactLightningModule(task_name, dtype="float64", first_state_chunks=6, first_state_val_chunks=1)
    task, generator = module.task, torch.Generator().manual_seed(0)
    state = task.sample(6, seed=0)
    x = torch.stack([state.x, state.x + 0.01], 1)  # (6, 2, P, d): chunks of two frames
    v = torch.stack([state.v, state.v], 1)
    states = module.first_states["train"]
    states.dx.copy_(0.01 * torch.randn(states.dx.shape, generator=generator, dtype=torch.float64))
    states.dv.copy_(0.01 * torch.randn(states.dv.shape, generator=generator, dtype=torch.float64))
    fx, fv = module.as_fitted("train", x, v)
    assert torch.equal(fx[:, 1:], x[:, 1:]) and torch.equal(fv[:, 1:], v[:, 1:])
    constraints = task.system.constraints
    if constraints.count == 0:
        assert torch.equal(fx[:, 0], x[:, 0] + states.dx) and torch.equal(fv[:, 0], v[:, 0] + states.dv)
        return
    assert float(constraints.phi(fx[:, 0]).abs().max()) < 1e-11
    J = constraints.jac(fx[:, 0])
    assert float((J @ fv[:, 0].reshape(6, -1, 1)).abs().max()) < 1e-12  # (velocities tangent)
    moved = (fx[:, 0] - x[:, 0]).abs().max()
    assert 0 < moved < 0.1  # (a correction, not a jump to another branch)
    # a step keeps the corrections as the moves they make: x0 + dx is on the constraints after it (RMSprop's
    # per-coordinate step leaves the tangent space, and the part off it would pile up)
    module._optimizer = lambda: SimpleNamespace(param_groups=[{"lr": module.config.lr}])
    index = torch.arange(6)
    grads = (torch.randn(x[:, 0].shape, generator=generator, dtype=torch.float64),) * 2
    module._move_first((x, v, None, None, index), "train", states.take(index), grads)
    assert float(constraints.phi(x[:, 0] + states.dx).abs().max()) < 1e-11
    # the projection is differentiable: the gradient the first states learn by agrees with finite differences
    dx0, dv0 = states.dx[:1].clone().requires_grad_(True), states.dv[:1].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda a, b: module._started(x[:1, 0], v[:1, 0], a, b), (dx0, dv0), eps=1e-6, atol=1e-5
    )


def test_on_noisy_ball_data_the_loss_least_over_the_first_states_prefers_the_true_restitution():
    # BP5-e (true e = 1) at noise 0.05: from the recorded first frames the loss of the true model is lower at e = 0,
    # the bias that made training learn e = 0; least over each chunk's first state (what training learns), it is
    # lower at the truth
    task = build_task("BP5-e")
    split = make_split(task, 100, seed=5, frames=40, noise=0.05, progress=False)
    x, v = torch.from_numpy(split["chunk_x"]).double(), torch.from_numpy(split["chunk_v"]).double()
    sim = simulator_for(task)
    torch.manual_seed(0)

    def losses(e: float) -> tuple[float, float]:
        params = task.params.replace(e=torch.full_like(task.params.e, e))
        states = FirstStates(len(x), x.shape[2], x.shape[3], torch.float64)
        index, recorded = torch.arange(len(x)), None
        for _ in range(60):
            dx, dv = states.take(index)
            px, pv, _ = sim.rollout(State(x[:, 0] + dx, v[:, 0] + dv), params, task.dt, x.shape[1])
            loss = 0.5 * ((px - x).abs().mean() + (pv - v).abs().mean())
            recorded = float(loss.detach()) if recorded is None else recorded
            loss.backward()
            states.update(index, dx.grad, dv.grad, lr=0.005)
        return recorded, float(loss.detach())

    (rec0, fit0), (rec1, fit1) = losses(0.0), losses(1.0)
    assert rec0 < rec1  # (the bias, from the recorded first frames)
    assert fit1 < fit0 < rec0  # (gone, least over the first states)
