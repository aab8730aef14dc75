"""Tensors follow the input's device in the physics path (float64, CPU only: no GPU needed).

With the default device set to "meta", every tensor made without ``device=`` lands on "meta", while the inputs
and parameters, all made beforehand, are on the CPU: an allocation that does not follow its inputs' device then
meets CPU tensors and raises (or leaves a "meta" tensor in the results, which the tests check for).  The results
must equal, bit for bit, those of the same calls with the default device left as it is."""

from __future__ import annotations

from contextlib import contextmanager

import pytest
import torch

import diffcontact as dc
from diffcontact.models.model import ContactModelNet, build_model
from diffcontact.state import State

FRAMES = 4  # frames of each rollout under test (frame 0 included)


@contextmanager
def default_device(device: str):
    """The default device inside the block, the previous one restored after it (also when the block raises)."""
    old = torch.get_default_device()
    torch.set_default_device(device)
    try:
        yield
    finally:
        torch.set_default_device(old)


def _on_cpu(*tensors: torch.Tensor) -> bool:
    return all(t.device.type == "cpu" for t in tensors)


def _state_before_contact(task, seed: int, batch: int = 4, limit: int = 100) -> State:
    """The states (CPU) one frame before the first contact of the sampled rollouts (``batch`` of them, from
    ``seed``) that have it first: the next frames have contacts (the ground truth, default device)."""
    sim = dc.simulator_for(task)
    state = task.sample(batch, seed)
    for _ in range(limit):
        after, hit = sim.step(state, task.params, task.dt)
        if hit.any():
            return State(state.x[hit].clone(), state.v[hit].clone())
        state = after
    raise AssertionError(f"{task.system.name}: no contact in {limit} frames")


# (task, a sampler seed whose rollouts reach a contact within a few frames)
TASKS = [("BP5-e", 0), ("BD5", 1), ("CP3", 0), ("Rope", 1), ("Gyro", 0), ("Cube", 2)]


@pytest.mark.parametrize("toi", [True, False], ids=["time-of-impact", "end-of-step"])
@pytest.mark.parametrize("name, seed", TASKS)
def test_a_rollout_with_contacts_follows_the_inputs_device(name, seed, toi):
    task = dc.build_task(name)
    state = _state_before_contact(task, seed)
    sim = dc.simulator_for(task, time_of_impact=toi)
    want = sim.rollout(state, task.params, task.dt, FRAMES)
    assert want[2][:, 1:].any(), "no contact in the frames under test"
    with default_device("meta"):
        got = sim.rollout(state, task.params, task.dt, FRAMES)
    assert _on_cpu(*got)
    for a, b in zip(got, want):
        assert torch.equal(a, b)


@pytest.mark.parametrize(
    "name, seed, model",
    [("BP5-e", 0, "CM-CD-CLNN"), ("BP5-e", 0, "CMr-CD-CHNN"), ("Cube", 2, "CM-CD-CLNN"), ("CubeToss", 2, "CM-CD-CLNN")],
)
def test_a_model_forward_and_backward_follow_the_inputs_device(name, seed, model):
    """A learnable model's rollout and its parameters' gradients (Lagrangian and Hamiltonian, exact and regularised
    contact model); Cube and CubeToss resolve contacts at their time of impact (their task files' default)."""
    task = dc.build_task(name)
    assert task.system.stepping.time_of_impact == name.startswith("Cube")
    state = _state_before_contact(task, seed)
    net = build_model(task, model, hidden=8, layers=1, seed=0)
    assert isinstance(net, ContactModelNet)

    def run():
        net.zero_grad()
        xs, vs = net(state.x, state.v, FRAMES)
        (xs.square().sum() + vs.square().sum()).backward()
        grads = [p.grad for p in net.parameters() if p.grad is not None]
        return xs.detach(), vs.detach(), grads

    with torch.no_grad():
        _, _, hit = net.simulator.rollout(state, net.params(), net.dt, FRAMES)
    assert hit[:, 1:].any(), "the model has no contact in the frames under test"
    want_x, want_v, want_g = run()
    assert want_g
    with default_device("meta"):
        got_x, got_v, got_g = run()
    assert _on_cpu(got_x, got_v, *got_g) and len(got_g) == len(want_g)
    assert torch.equal(got_x, want_x) and torch.equal(got_v, want_v)
    for a, b in zip(got_g, want_g):
        assert torch.equal(a, b)
