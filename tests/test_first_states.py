"""Learned first states of noisy chunks (train/first_states.py): the update touches only a batch's chunks, by
RMSprop; and on BP5-e at noise 0.05 the loss least over the first states prefers the true e where the loss from
the recorded first frames prefers e = 0."""

from __future__ import annotations

import pytest
import torch

from diffcontact.data.generate import generate_dataset, make_split
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems.registry import build_task
from diffcontact.train.config import TrainConfig
from diffcontact.train.first_states import BETA, FirstStates
from diffcontact.train.run import _data, first_state_settings


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
    # the leaves a batch takes, and every chunk with its first frame corrected
    dx, dv = states.take(index)
    assert dx.requires_grad and torch.equal(dx.detach(), states.dx[index])
    x = torch.randn(5, 4, 2, 3, dtype=torch.float64)
    cx, cv = states.corrected(x, x)
    assert torch.equal(cx[:, 0], x[:, 0] + states.dx) and torch.equal(cx[:, 1:], x[:, 1:])
    assert torch.equal(cv[:, 0], x[:, 0] + states.dv)


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


@pytest.mark.parametrize("task_name, learned", [("BP1", True), ("CP1-wall", False), ("BD1", False)])
def test_first_states_are_learned_on_noisy_data_of_free_points_only(task_name, learned, tmp_path):
    # (on the chain pendulum, corrected first states projected back onto the constraints made μ, e and the 5-step
    # error worse: docs/training.md, "Noisy data")
    generate_dataset(task_name, tmp_path, n_train=4, n_val=2, n_test=2, noise=0.05, progress=False)
    config = TrainConfig(task=task_name, data_root=str(tmp_path))
    settings = first_state_settings(config, _data(config))
    assert (settings["first_state_chunks"] > 0) == learned and (settings["first_state_lr"] > 0) == learned
