"""A float32 model's contact events: its problems are assembled and solved in float64, so that an ill-conditioned
event (a rope link compressed to almost nothing: the largest of A's diagonal 1e8 times its least eigenvalue) gives the
float64 answer of its float32 state, not one made of rounding."""

from __future__ import annotations

from dataclasses import replace

import torch

from diffcontact.simulator import simulator_for
from diffcontact.systems import build_task


def _crushed_rope(count: int = 8, length: float = 1e-4) -> tuple[torch.Tensor, torch.Tensor]:
    """Rope states (count, 10, 2) with link 4→5 shortened to 1e-4 m and turned a right angle from link 3→4 (both its
    bend limits crossed, their rows about 1e4 per m) and velocities of about 1 m/s: float64."""
    task = build_task("Rope")
    state = task.sample(count, seed=3)
    x, v = state.x.clone(), state.v.clone()
    gen = torch.Generator().manual_seed(0)
    before = x[:, 4] - x[:, 3]
    turned = torch.stack([-before[:, 1], before[:, 0]], -1)
    shift = x[:, 5] - x[:, 4] - length * turned / turned.norm(dim=-1, keepdim=True)
    x[:, 5:] -= shift[:, None]  # (the rest of the rope follows node 5)
    v = v + torch.randn(v.shape, generator=gen, dtype=v.dtype)
    return x, v


def test_a_float32_state_gets_the_float64_impulses_of_its_values():
    task = build_task("Rope")
    sim = simulator_for(task)
    x, v = _crushed_rope()
    x32, v32 = x.float(), v.float()
    contacts = task.system.detector.detect(x32.double())
    assert contacts is not None
    A = sim.contact_model.phases(task.system.constraints, task.params, x32.double(), v32.double(), contacts, task.dt).A
    eig = torch.linalg.eigvalsh(A)
    assert float((A.diagonal(dim1=-2, dim2=-1).amax(-1) / eig[:, 0]).amin()) > 1e7  # (ill-conditioned, as meant)
    wide, _ = sim.contact_model(task.system, task.params, x32.double(), v32.double(), task.dt)
    params32 = task.params.replace(mu=task.params.mu.float(), e=task.params.e.float())
    narrow, _ = sim.contact_model(task.system, params32, x32, v32, task.dt)
    assert narrow.dtype == torch.float32
    torch.testing.assert_close(narrow.double(), wide, rtol=1e-5, atol=1e-5)


def test_a_float32_state_gets_the_float64_gradients_of_its_values():
    task = build_task("Rope")
    sim = simulator_for(task)
    x, v = _crushed_rope(4)
    weights = torch.randn(v.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = []
    for dtype in (torch.float32, torch.float64):
        masses = task.params.inertia.masses.to(dtype).requires_grad_(True)
        params = task.params.replace(
            inertia=replace(task.params.inertia, masses=masses, moments=task.params.inertia.moments.to(dtype)),
            mu=task.params.mu.to(dtype),
            e=task.params.e.to(dtype),
        )
        vel = v.float().to(dtype).requires_grad_(True)
        after, _ = sim.contact_model(task.system, params, x.float().to(dtype), vel, task.dt)
        grads.append(torch.autograd.grad((after.double() * weights).sum(), (vel, masses)))
    for narrow, wide in zip(*grads):
        torch.testing.assert_close(narrow.double(), wide, rtol=1e-4, atol=1e-4)
