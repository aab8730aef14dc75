"""Finite-difference gradients (float64 gradcheck) through the regularised contact model (CMr) and through the
Hamiltonian (CHNN) path of the Simulator, and the solver's backward pass in float32 against float64."""

from __future__ import annotations

import pytest
import torch

from diffcontact.config import task_from_dict
from diffcontact.simulator import simulator_for
from diffcontact.solver import solve_cone_qp
from diffcontact.state import Inertia, State
from diffcontact.systems import build_task

F64 = torch.float64
CMR_REG = 0.01
GRADCHECK = dict(eps=1e-6, atol=1e-6, rtol=1e-6)  # finite-difference step and tolerances (float64)
FLOAT32_GRAD_TOL = 2e-6  # float32 vs float64 gradients, relative to max(1, |g|) per element (measured: 4.6e-7)


def _disk_on_floor(mu: float, cor: float, gravity: float = 9.81):
    """One disk (r = 0.1 m, 1 kg) over the floor y = 0; contacts at the end of each step; no penetration
    compensation (its target velocity is computed without gradient, by design: finite differences would see it)."""
    raw = {
        "task": {"name": "disk", "system": "bouncing", "dt": 0.01, "frames": 10},
        "bodies": {"kind": "disk", "masses": [1.0], "radii": [0.1]},
        "walls": {"lines": [[0.0, 1.0, 0.0]]},
        "potential": {"gravity": gravity},
        "contact": {"mu": [mu], "cor": [cor], "time_of_impact": False, "compensation": 0.0},
    }
    return build_task(task_from_dict(raw))


def _disk_state(task, centre, velocity, omega):
    """A State of the disk task from its centre (2,), centre velocity (2,) and spin (rad/s), via its sampler's
    point layout (centre, then two points on orthogonal axes at distance a)."""
    s = task.sample(1, seed=0)
    c0 = s.x[0, 0]
    offsets = s.x[0] - c0  # (3, 2): the body's points relative to its centre
    x = torch.tensor(centre, dtype=F64) + offsets
    rot = torch.stack([-offsets[:, 1], offsets[:, 0]], -1)  # ω × r
    v = torch.tensor(velocity, dtype=F64) + omega * rot
    return x[None], v[None]


def _params_fn(task, mu, e, masses, moments):
    return task.params.replace(inertia=Inertia(masses, moments), mu=mu, e=e)


@pytest.mark.parametrize("mu, vx", [(0.2, 1.0), (1.0, 0.2)])  # sliding through the impact, and sticking
def test_cmr_contact_step_passes_gradcheck(mu, vx):
    """One frame of the CMr model (A + 0.01 I in both phases) with a disk striking the floor: gradcheck in the
    velocities, μ, e, the mass and the moments."""
    task = _disk_on_floor(mu=mu, cor=0.5)
    sim = simulator_for(task, reg=CMR_REG)
    x, v = _disk_state(task, [0.5, 0.1 - 1e-3], [vx, -1.0], 2.0)
    p = task.params

    def step(v, mu, e, masses, moments):
        state, hit = sim.step(State(x, v), _params_fn(task, mu, e, masses, moments), task.dt)
        assert bool(hit.all())
        return state.x, state.v

    inputs = [t.clone().requires_grad_() for t in (v, p.mu, p.e, p.inertia.masses, p.inertia.moments)]
    assert torch.autograd.gradcheck(step, inputs, **GRADCHECK)


def test_hamiltonian_rollout_with_an_impact_passes_gradcheck():
    """Five frames of the constrained Hamiltonian dynamics (CHNN's path) of a disk falling onto the floor, one
    impact in the middle (CM): gradcheck in the initial state, μ, e, the mass and the moments."""
    task = _disk_on_floor(mu=0.3, cor=0.6)
    sim = simulator_for(task, dynamics="hamiltonian")
    x0, v0 = _disk_state(task, [0.5, 0.115], [0.8, -0.9], 1.0)
    p = task.params

    def rollout(x0, v0, mu, e, masses, moments):
        xs, vs, hit = sim.rollout(State(x0, v0), _params_fn(task, mu, e, masses, moments), task.dt, 5)
        assert bool(hit.any()) and not bool(hit[:, -1].any())
        return xs[:, -1], vs[:, -1]

    inputs = [t.clone().requires_grad_() for t in (x0, v0, p.mu, p.e, p.inertia.masses, p.inertia.moments)]
    assert torch.autograd.gradcheck(rollout, inputs, **GRADCHECK)


def test_solver_backward_in_float32_matches_float64():
    """Gradients of w·f with respect to A, q, μ and lower from float32 inputs equal the float64 ones rounded to
    float32 accuracy (the solver and its backward pass run in float64 either way)."""
    gen = torch.Generator().manual_seed(7)
    B, K, d = 16, 3, 3
    n = K * d
    M = torch.randn(B, n, n, generator=gen, dtype=F64)
    A = M @ M.mT / n + 0.2 * torch.eye(n, dtype=F64)
    q = torch.randn(B, n, generator=gen, dtype=F64)
    mu = 0.2 + torch.rand(B, K, generator=gen, dtype=F64)
    lower = 0.3 * torch.rand(B, K, generator=gen, dtype=F64)
    w = torch.randn(B, n, generator=gen, dtype=F64)
    grads = {}
    for dtype in (torch.float32, torch.float64):
        ins = [t.to(dtype).requires_grad_() for t in (A, q, mu, lower)]
        f = solve_cone_qp(*ins)
        assert f.dtype == dtype
        (f * w.to(dtype)).sum().backward()
        grads[dtype] = [t.grad.double() for t in ins]
    for name, g32, g64 in zip(("A", "q", "mu", "lower"), grads[torch.float32], grads[torch.float64]):
        scale = g64.abs().amax(-1, keepdim=True).clamp_min(1.0)
        assert ((g32 - g64).abs() / scale).max().item() < FLOAT32_GRAD_TOL, name
