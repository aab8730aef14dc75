"""The rope-scaling tasks Rope50, Rope100 and Rope200 (the published ER{n}k50): their values, their simulation, and
the contact problems of a 200-node rope (up to 399 limits at once) against Clarabel, with gradients against central
differences (float64)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from solver_oracle import TOL_F, TOL_OBJ, clarabel_solve, kkt_residual

from diffcontact.simulator import simulator_for
from diffcontact.state import Inertia
from diffcontact.systems import build_task

LONG_ROPES = [("Rope50", 50), ("Rope100", 100), ("Rope200", 200)]


@pytest.mark.parametrize("name, nodes", LONG_ROPES)
def test_long_rope_values(name, nodes):
    task = build_task(name)
    system = task.system
    # a bend limit between each two links (nodes − 1) and a stretch limit on each link (nodes, the first to the
    # anchor), each with two sides sharing its slot
    assert (system.n_points, system.d, system.constraints.count) == (nodes, 2, 0)
    assert (system.detector.count, system.n_slots) == (2 * (2 * nodes - 1), 2 * nodes - 1)
    assert (task.dt, task.frames) == (0.005, 100)
    assert torch.equal(task.params.inertia.masses, torch.full((nodes,), 0.1, dtype=torch.float64))
    assert task.params.mu.eq(0).all() and task.params.e.eq(0).all()
    # the spring k = 50 (V = k (|l| − l0)², no ½) and gravity: one link stretched by 1 cm from a rope at rest
    x = torch.zeros(1, nodes, 2, dtype=torch.float64)
    x[0, :, 0] = 0.05 * torch.arange(1, nodes + 1, dtype=torch.float64)
    stretched = x.clone()
    stretched[0, -1, 0] += 0.01
    dV = task.params.potential_energy(stretched) - task.params.potential_energy(x)
    assert dV.item() == pytest.approx(50.0 * 0.01**2, rel=1e-12)


@pytest.mark.parametrize("name, nodes", LONG_ROPES)
def test_long_rope_flow_conserves_energy(name, nodes):
    """Between contact events a rope is springs and gravity: RK4 at a quarter of the task's dt keeps the energy to
    1e-6 of its size over 100 steps (without the limits' events, which remove energy: e = 0)."""
    task = build_task(name)
    sim = simulator_for(task)
    s = task.sample(4, seed=7)
    x, v = s.x, s.v
    E0 = task.system.energy(task.params, x, v)
    with torch.no_grad():
        for _ in range(100):
            x, v = sim.flow(task.params, x, v, task.dt / 4)
    E = task.system.energy(task.params, x, v)
    assert ((E - E0).abs() / E0.abs()).max().item() < 1e-6


def _compressed_zigzag(nodes: int, ratio: float = 0.7, turn: float = 0.3) -> torch.Tensor:
    """(1, nodes, 2) positions hanging from the anchor: every link ``ratio`` of its rest length (0.05 m) and every
    joint bent by ``turn`` rad, alternating: past every stretch limit (0.8) and every bend limit (0.2 rad)."""
    angle = -math.pi / 2 + turn / 2 * torch.where(torch.arange(nodes) % 2 == 0, 1.0, -1.0).double()
    steps = ratio * 0.05 * torch.stack([angle.cos(), angle.sin()], -1)
    return steps.cumsum(0)[None]


def _phases(task, params, x, v):
    sim = simulator_for(task)
    contacts = task.system.detector.detect(x)
    return sim.contact_model.phases(task.system.constraints, params, x, v, contacts, task.dt), contacts


@pytest.mark.parametrize("state", ["every limit crossed", "every limit crossed, float32 state", "simulated"])
def test_rope200_contact_problems_match_clarabel_and_central_differences(state):
    """A 200-node rope's limit problems: the compressed zigzag crosses all 399 limits (A 399 × 399, eigenvalues 6e-4
    … 1.3e5: the least is real, not rounding), also as a float32 state (a float32 model's: its problem is assembled
    and solved in float64, and its least eigenvalue is as real), and a simulated frame has the limits that 60 frames
    of motion bring (with random velocities).
    Both phases agree with Clarabel, and (float64) the velocity jump's derivatives with respect to the velocities and
    the masses agree with central differences."""
    task = build_task("Rope200")
    gen = torch.Generator().manual_seed(3)
    if state.startswith("every limit crossed"):
        x = _compressed_zigzag(200)
        v = 0.3 * torch.randn(1, 200, 2, generator=gen, dtype=torch.float64)
        if state.endswith("float32 state"):
            x, v = x.float(), v.float()
    else:
        s = task.sample(2, seed=3)
        sim, x, v = simulator_for(task), s.x, s.v
        with torch.no_grad():
            for _ in range(60):
                x, v = sim.flow(task.params, x, v, task.dt)
                v, _ = sim.contact_model(task.system, task.params, x, v, task.dt)
        # (at rest on its limits every contact is at a touch/separate switch, where the derivative is one-sided:
        # velocities that close some limits and open others make a problem with a derivative)
        v = v + 0.3 * torch.randn(v.shape, generator=gen, dtype=torch.float64)
    phases, contacts = _phases(task, task.params, x, v)
    K = int(contacts.active.sum(-1).max())
    assert K == 399 if state.startswith("every limit crossed") else K >= 50
    model = simulator_for(task).contact_model
    target = model.target_velocity(task.system.constraints, x[contacts.index].double(), contacts, task.dt, phases.A)
    after = phases.v_before + (phases.A @ phases.f_c[..., None])[..., 0]  # (the compression's end)
    for b in range(len(contacts.index)):
        on = contacts.active[b].numpy()
        A = phases.A[b].numpy()[np.ix_(on, on)]
        for f, q, lower in (
            (phases.f_c[b], phases.v_before[b], np.zeros(on.sum())),
            (phases.f_r[b], after[b] - target[b], phases.lower[b].numpy()[on]),
        ):
            q, f, mu = q.numpy()[on], f.numpy()[on], np.zeros(on.sum())
            ref, _ = clarabel_solve(A, q, mu, lower, 1)
            # (Clarabel's own residual at its tolerance reaches 3e-8 on the simulated frames, where our answer's
            # objective is lower than its own: the answer is compared to its accuracy, and by objective)
            assert kkt_residual(A, q, mu, lower, f, 1) <= 1e-9
            scale = max(1.0, np.abs(ref).max())
            assert np.abs(f - ref).max() <= (TOL_F + 100 * kkt_residual(A, q, mu, lower, ref, 1)) * scale
            obj, obj_ref = 0.5 * f @ A @ f + q @ f, 0.5 * ref @ A @ ref + q @ ref
            assert obj <= obj_ref + TOL_OBJ * max(1.0, abs(obj_ref), np.abs(q).max() * scale)

    if x.dtype != torch.float64:
        return
    # the velocity jump's derivatives: along a random velocity and a random change of the 200 masses
    w = torch.randn(x.shape[0], 400, generator=gen, dtype=torch.float64)
    dv = torch.randn(v.shape, generator=gen, dtype=torch.float64)
    dm = torch.randn(200, generator=gen, dtype=torch.float64)
    masses = task.params.inertia.masses

    def jump(v, m):
        params = task.params.replace(inertia=Inertia(masses=m, moments=task.params.inertia.moments))
        phases, contacts = _phases(task, params, x, v)
        return (w[contacts.index] * phases.velocity_change()).sum()

    v0, m0 = v.clone().requires_grad_(True), masses.clone().requires_grad_(True)
    g_v, g_m = torch.autograd.grad(jump(v0, m0), (v0, m0))
    h = 1e-4  # (relative to the masses; the restitution phase's solver accuracy dominates below it)
    with torch.no_grad():
        fd_v = (jump(v + h * dv, masses) - jump(v - h * dv, masses)) / (2 * h)
        fd_m = (jump(v, masses * (1 + h * dm)) - jump(v, masses * (1 - h * dm))) / (2 * h)
    assert (g_v * dv).sum().item() == pytest.approx(fd_v.item(), rel=1e-4, abs=1e-8)
    assert (g_m * masses * dm).sum().item() == pytest.approx(fd_m.item(), rel=1e-4, abs=1e-8)
