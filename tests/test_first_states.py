"""Learned first states of noisy chunks (train/first_states.py): the update touches only a batch's chunks, by
RMSprop; and on BP5-e at noise 0.05 the loss least over the first states prefers the true e where the loss from
the recorded first frames prefers e = 0."""

from __future__ import annotations

import math

import pytest
import torch

from diffcontact.data.generate import generate_dataset, make_split
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems.registry import build_task
from diffcontact.train.config import TrainConfig
from diffcontact.train.first_states import GROW, MIN_SCALE, SHRINK, FirstStates
from diffcontact.train.run import NOISY_COEF_LR, _data, first_state_settings


def test_a_step_moves_only_the_chunks_of_the_batch_and_only_where_it_lowers_the_chunk_loss():
    states = FirstStates(5, (2, 3), torch.float64)
    index = torch.tensor([1, 3])
    gx, gv = torch.randn(2, 2, 3, dtype=torch.float64), torch.randn(2, 2, 3, dtype=torch.float64)
    tried = []

    def loss_at(values):  # (the chunks' losses at the trial corrections, one per call)
        def at(dx, dv):
            tried.append((dx.clone(), dv.clone()))
            return torch.tensor(values, dtype=torch.float64)

        return at

    moved = states.update(index, gx, gv, 0.01, torch.tensor([1.0, 1.0]), loss_at([0.5, 0.5]))
    # the trial: every entry moved by lr against its gradient's sign; kept where the loss fell
    assert torch.equal(tried[0][0], -0.01 * gx.sign()) and torch.equal(tried[0][1], -0.01 * gv.sign())
    assert moved.tolist() == [True, True] and torch.equal(states.dx[index], -0.01 * gx.sign())
    untouched = torch.tensor([0, 2, 4])
    assert states.dx[untouched].abs().max() == 0 and states.steps.tolist() == [0, 1, 0, 1, 0]
    # a trial that raises chunk 1's loss is not taken, and its step is halved; chunk 3 moves by a full step
    moved = states.update(index, gx, gv, 0.01, torch.tensor([0.5, 0.5]), loss_at([0.7, 0.4]))
    assert moved.tolist() == [False, True] and states.scale.tolist() == [1, SHRINK, 1, 1, 1]
    assert torch.equal(states.dx[1], -0.01 * gx[0].sign()) and torch.allclose(states.dx[3], -0.02 * gx[1].sign())
    # chunk 1's next trial is of the halved step, and once taken its step grows by GROW
    states.update(index[:1], gx[:1], gv[:1], 0.01, torch.tensor([0.5]), loss_at([0.4]))
    assert torch.allclose(tried[-1][0], -(0.01 + 0.01 * SHRINK) * gx[:1].sign())
    assert torch.allclose(states.dx[1], -(0.01 + 0.01 * SHRINK) * gx[0].sign()) and states.scale[1] == SHRINK * GROW
    assert states.steps.tolist() == [0, 3, 0, 2, 0] and states.dx[untouched].abs().max() == 0
    for _ in range(8):  # (trials never kept: the step shrinks to MIN_SCALE, not to nothing)
        states.update(index[1:], gx[1:], gv[1:], 0.01, torch.tensor([0.1]), loss_at([0.2]))
    assert states.scale[3] == MIN_SCALE and torch.allclose(states.dx[3], -0.02 * gx[1].sign())
    # the leaves a batch takes, and every chunk with its first frame corrected
    dx, dv = states.take(index)
    assert dx.requires_grad and torch.equal(dx.detach(), states.dx[index])
    x = torch.randn(5, 4, 2, 3, dtype=torch.float64)
    cx, cv = states.corrected(x, x)
    assert torch.equal(cx[:, 0], x[:, 0] + states.dx) and torch.equal(cx[:, 1:], x[:, 1:])
    assert torch.equal(cv[:, 0], x[:, 0] + states.dv)


def test_first_states_saved_by_the_earlier_rmsprop_rule_load_with_full_steps():
    saved = {"dx": torch.ones(4, 3), "dv": torch.ones(4, 3), "square": torch.ones(4, 2, 3), "steps": torch.ones(4)}
    states = FirstStates(4, (3,), torch.float32)
    states.load_state_dict(saved)
    assert torch.equal(states.dx, torch.ones(4, 3)) and torch.equal(states.scale, torch.ones(4))


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
        states = FirstStates(len(x), tuple(x.shape[2:]), torch.float64)

        def chunk_losses(dx: torch.Tensor, dv: torch.Tensor) -> torch.Tensor:
            px, pv, _ = sim.rollout(State(x[:, 0] + dx, v[:, 0] + dv), params, task.dt, x.shape[1])
            return 0.5 * ((px - x).abs().flatten(1).mean(1) + (pv - v).abs().flatten(1).mean(1))

        index, recorded, steps = torch.arange(len(x)), None, 100
        for step in range(steps):
            dx, dv = states.take(index)
            chunks = chunk_losses(dx, dv)
            recorded = float(chunks.detach().mean()) if recorded is None else recorded
            chunks.mean().backward()
            share = 0.5 * (1 + math.cos(math.pi * step / steps))  # (the cosine schedule of training)
            states.update(index, dx.grad, dv.grad, 0.005 * share, chunks.detach(), chunk_losses)
        with torch.no_grad():
            return recorded, float(chunk_losses(states.dx, states.dv).mean())

    (rec0, fit0), (rec1, fit1) = losses(0.0), losses(1.0)
    assert rec0 < rec1  # (the bias, from the recorded first frames)
    assert fit1 < fit0 < rec0  # (gone, least over the first states)


def test_on_the_chain_pendulum_a_first_state_is_corrected_in_its_link_angles_and_stays_on_the_constraints():
    task = build_task("CP3-e")
    system = task.system
    split = make_split(task, 6, seed=2, frames=10, noise=0.05, progress=False)
    x0, v0 = (torch.from_numpy(split[k][:, 0]).double() for k in ("chunk_x", "chunk_v"))
    states = FirstStates(len(x0), (system.noise_coordinates.size,), torch.float64, system.noise_coordinates)
    assert states.dx.shape == (6, 3)
    same = states.start(x0, v0, states.dx, states.dv)  # (no correction: the recorded frame)
    assert torch.allclose(same[0], x0, atol=1e-12) and torch.allclose(same[1], v0, atol=1e-12)
    dx, dv = 0.05 * torch.randn(6, 3, dtype=torch.float64), 0.05 * torch.randn(6, 3, dtype=torch.float64)
    x, v = states.start(x0, v0, dx, dv)
    assert (x - x0).abs().max() > 1e-3  # (moved, and still on the chain: links of their lengths, J_E v = 0)
    assert system.constraints.phi(x).abs().max() < 1e-12
    assert (system.constraints.jac(x) @ v.reshape(6, -1, 1)).abs().max() < 1e-12
    q, w = system.noise_coordinates.from_cartesian(x, v)
    q0, w0 = system.noise_coordinates.from_cartesian(x0, v0)
    assert torch.allclose(q - q0, dx, atol=1e-12) and torch.allclose(w - w0, dv, atol=1e-12)


@pytest.mark.parametrize("task_name, learned", [("BP1", True), ("CP1-wall", True), ("BD1", False)])
def test_first_states_are_learned_where_the_noise_is_iid_in_known_coordinates(task_name, learned, tmp_path):
    # (free points in Cartesian coordinates, the chain pendulum in its link angles; not where the noise was
    # projected onto the constraints: the disks, the gyroscope)
    generate_dataset(task_name, tmp_path, n_train=4, n_val=2, n_test=2, noise=0.05, progress=False)
    config = TrainConfig(task=task_name, data_root=str(tmp_path))
    settings = first_state_settings(config, _data(config))
    assert (settings["first_state_chunks"] > 0) == learned and (settings["first_state_lr"] > 0) == learned
    # (with μ and e at the full rate, unless the command or the task file gives their rate)
    assert settings.get("coef_lr") == (NOISY_COEF_LR if learned else None)
    assert "coef_lr" not in first_state_settings(config, _data(config), coef_given=True)
