"""Conservation in the elastic frictionless tasks, and end-to-end gradients (μ, e, masses, moments) vs finite
differences (float64)."""

from __future__ import annotations

import pytest
import torch

from diffcontact.dynamics.potentials import Gravity, SumPotential
from diffcontact.simulator import simulator_for
from diffcontact.state import Inertia, Params, State
from diffcontact.systems import build_task

ENERGY_TOL = 1e-6  # relative energy change over 100 steps when RK4 is accurate on the time scale
FD_STEP = 1e-5
FD_RTOL = 1e-4  # central differences (O(h²) ~ 1e-10) + solver accuracy (~1e-11 / h)

# (task, overrides that make impacts happen within 100 fine steps, dt divisor)
CONSERVATIVE = [
    ("BP5-e", None, 1),  # free flight is integrated exactly: only the contact model can change the energy
    ("CP3-e", {"walls": {"lines": [[0.0, 1.0, 0.5]]}}, 8),
    ("Gyro-e", {"walls": {"planes": [[0.0, 1.0, 0.0, 0.15]]}}, 8),
]


def _energy(task, x, v):
    B, T = x.shape[:2]
    return task.system.energy(task.params, x.flatten(0, 1), v.flatten(0, 1)).reshape(B, T)


@pytest.mark.parametrize("name, overrides, div", CONSERVATIVE)
def test_elastic_frictionless_tasks_conserve_energy(name, overrides, div):
    task = build_task(name, overrides=overrides)
    s = task.sample(16, seed=11)
    with torch.no_grad():
        x, v, hit = simulator_for(task).rollout(s, task.params, task.dt / div, 101)
    assert int(hit.sum()) >= 2, "the test needs impacts"
    E = _energy(task, x, v)
    rel = ((E - E[:, :1]).abs() / E[:, :1].abs()).max().item()
    assert rel < ENERGY_TOL, rel


@pytest.mark.parametrize("name, overrides", [(c[0], c[1]) for c in CONSERVATIVE[1:]])
def test_energy_error_at_task_dt_is_integration_error(name, overrides):
    """At the task's dt the energy error is not negligible (measured), but it shrinks at least 8× when dt is
    halved (RK4: ~16×), so it is integration error, not the contact model."""
    task = build_task(name, overrides=overrides)
    s = task.sample(16, seed=11)
    errs = []
    for div in (2, 4):
        with torch.no_grad():
            x, v, _ = simulator_for(task).rollout(s, task.params, task.dt / div, 100 * div // 2 + 1)
        E = _energy(task, x, v)
        errs.append(((E - E[:, :1]).abs() / E[:, :1].abs()).max().item())
    assert errs[0] / errs[1] > 8.0, errs


def _bp_case():
    from diffcontact.config import task_from_dict

    raw = {
        "task": {"name": "grad", "system": "bouncing", "dt": 0.01, "frames": 8},
        "bodies": {"kind": "point", "masses": [0.3, 0.5], "radii": [0.1, 0.12]},
        "walls": {"lines": [[0.0, 1.0, 0.0]]},
        "potential": {"gravity": 9.81},
        "contact": {"mu": [0.2, 0.3, 0.4], "cor": [0.6, 0.7, 0.8], "time_of_impact": False},
    }
    task = build_task(task_from_dict(raw))
    # ball 1 hits ball 0 obliquely (sliding friction) at step 3, nowhere near a touch/separate switch
    x = torch.tensor([[[0.4, 0.5], [0.6, 0.56]]], dtype=torch.float64)
    v = torch.tensor([[[0.5, 0.0], [-2.0, 1.5]]], dtype=torch.float64)
    return task, State(x, v), 8


def _cp_case():
    """A chain-pendulum trajectory with one isolated sliding bounce (μ = 0.05, e = 0.6), cut 4 frames before it."""
    task = build_task("CP3", overrides={"walls": {"lines": [[0.0, 1.0, 0.8]]}, "contact": {"cor": [0.6], "mu": [0.05]}})
    s = task.sample(8, seed=3)
    with torch.no_grad():
        x, v, hit = simulator_for(task).rollout(s, task.params, task.dt, 40)
    for b in range(8):
        frames = torch.nonzero(hit[b]).flatten().tolist()
        if frames and frames[0] >= 4 and (len(frames) == 1 or frames[1] > frames[0] + 4):
            k = frames[0]
            return task, State(x[b : b + 1, k - 4], v[b : b + 1, k - 4]), 12
    raise AssertionError("no isolated bounce found")


def _bd_case():
    """A spinning disk hits a sliding disk (friction, restitution) in zero gravity; moments enter via spin."""
    from diffcontact.config import task_from_dict
    from diffcontact.systems.bouncing import disk_points

    raw = {
        "task": {"name": "grad-bd", "system": "bouncing", "dt": 0.01, "frames": 8},
        "bodies": {"kind": "disk", "masses": [0.2, 0.4], "radii": [0.1, 0.15]},
        "walls": {"lines": [[0.0, 1.0, 0.0]]},
        "potential": {"gravity": 9.81},
        "contact": {"mu": [0.15, 0.3, 0.4], "cor": [0.5, 0.7, 0.8], "time_of_impact": False},
    }
    task = build_task(task_from_dict(raw))
    f64 = torch.float64
    x, v = disk_points(
        torch.tensor([[[0.4, 0.5], [0.62, 0.58]]], dtype=f64),
        torch.tensor([[0.3, 1.0]], dtype=f64),
        torch.tensor([[[0.6, 0.0], [-1.5, 0.5]]], dtype=f64),
        torch.tensor([[4.0, -2.0]], dtype=f64),
    )
    return task, State(x, v), 8


@pytest.mark.parametrize("case", [_bp_case, _cp_case, _bd_case])
def test_rollout_gradients_match_finite_differences(case):
    task, s, steps = case()
    sim = simulator_for(task)
    q = task.system.points_per_body
    base = task.params

    def final(mu, e, masses, moments):
        pot = SumPotential(Gravity(9.81, torch.tensor([0.0, 1.0], dtype=torch.float64), q))
        params = Params(Inertia(masses, moments), pot, mu, e)
        x, v, hit = sim.rollout(s, params, task.dt, steps)
        return x[:, -1], v[:, -1], hit

    args = [base.mu.clone(), base.e.clone(), base.inertia.masses.clone(), base.inertia.moments.clone()]
    with torch.no_grad():
        _, _, hit = final(*args)
    assert hit.any() and not hit[:, -2:].any(), "needs one impact away from the window's end"
    w = torch.randn(2, *s.x.shape[1:], generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def loss(*a):
        x, v, _ = final(*a)
        return (w[0] * x[0]).sum() + (w[1] * v[0]).sum()

    leaves = [a.clone().requires_grad_(True) for a in args]
    grads = torch.autograd.grad(loss(*leaves), leaves, allow_unused=True)
    grads = [torch.zeros_like(a) if g is None else g for a, g in zip(args, grads)]
    for k, (arg, grad) in enumerate(zip(args, grads)):
        fd = torch.zeros_like(arg)
        for i in range(arg.numel()):  # a few parameters: finite differences, not a hot path
            plus, minus = [a.clone() for a in args], [a.clone() for a in args]
            plus[k].view(-1)[i] += FD_STEP
            minus[k].view(-1)[i] -= FD_STEP
            with torch.no_grad():
                fd.view(-1)[i] = (loss(*plus) - loss(*minus)) / (2 * FD_STEP)
        torch.testing.assert_close(grad, fd, rtol=FD_RTOL, atol=1e-7)
        if arg.numel():
            assert grad.abs().max() > 1e-4  # the parameter actually matters here
