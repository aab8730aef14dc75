"""Constrained dynamics (float64): Jacobians vs autograd, closed-form inertia, RK4 order, CLNN = CHNN,
constraint drift."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev, vmap

from diffcontact.dynamics.hamiltonian import hamiltonian_field, momentum
from diffcontact.dynamics.inertia import apply_blocks, body_blocks, dense, kinetic_energy
from diffcontact.dynamics.lagrangian import lagrangian_field
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems import build_task

JAC_TOL = 1e-14  # closed-form vs autograd derivatives (float64 rounding; measured: equal)
DRIFT_TOL = 1e-6  # |Φ| after 100 steps


pytestmark = pytest.mark.usefixtures("float64_default")  # (tests/conftest.py)


def _random_tangent(task, x, gen):
    """Random velocities satisfying J_E v = 0 (rigid and jointed motions), (B, P, d)."""
    B, P, d = x.shape
    v = torch.randn(B, P * d, 1, generator=gen)
    cons = task.system.constraints
    if cons.count:
        J = cons.jac(x)
        v = v - J.mT @ torch.linalg.solve(J @ J.mT, J @ v)
    return v.reshape(B, P, d)


@pytest.mark.parametrize("name", ["CP3", "BD5", "Gyro"])
def test_constraint_jacobians_match_autograd(name):
    task = build_task(name)
    x = task.sample(3, seed=0).x
    cons = task.system.constraints
    P, d = x.shape[1:]
    auto = vmap(jacrev(lambda y: cons.phi(y[None])[0]))(x).reshape(3, cons.count, P * d)
    torch.testing.assert_close(cons.jac(x), auto, atol=JAC_TOL, rtol=0)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(1))
    jv = vmap(jacrev(lambda y, w: cons.jac(y[None])[0] @ w.reshape(-1)), in_dims=(0, 0))(x, v)
    torch.testing.assert_close(cons.jac_dot(x, v), jv.reshape(3, cons.count, P * d), atol=JAC_TOL, rtol=0)


@pytest.mark.parametrize("name", ["BP5", "BD5", "CP3", "Rope", "Gyro"])
def test_contact_normal_rows_are_gap_rates(name):
    """For admissible velocities, the normal row of every candidate gives d(gap)/dt (autograd oracle)."""
    task = build_task(name)
    gen = torch.Generator().manual_seed(2)
    x = task.sample(4, seed=3).x
    v = _random_tangent(task, x, gen)
    det = task.system.detector
    grad = vmap(jacrev(lambda y: det.gaps(y[None])[0]))(x)  # (B, K, P, d)
    rate = (grad * v[:, None]).flatten(2).sum(-1)
    rows = det.jacobian(x)[:, :, 0]  # (B, K, D)
    torch.testing.assert_close((rows @ v.reshape(4, -1, 1))[..., 0], rate, atol=1e-9, rtol=1e-9)


def test_disk_inertia_closed_form():
    """½vᵀMv of a disk from its 3 points equals ½ m |v_c|² + ½ (m r²/2) ω², and M M⁻¹ = I."""
    from diffcontact.systems.bouncing import disk_points

    task = build_task("BD5")
    inertia = task.params.inertia
    M, Minv = body_blocks(inertia)
    torch.testing.assert_close(M @ Minv, torch.eye(3).expand(5, 3, 3), atol=1e-12, rtol=0)
    gen = torch.Generator().manual_seed(0)
    vc, w = torch.randn(2, 5, 2, generator=gen), torch.randn(2, 5, generator=gen)
    _, v = disk_points(torch.rand(2, 5, 2, generator=gen), torch.rand(2, 5, generator=gen), vc, w)
    m, r = inertia.masses, torch.tensor([0.05, 0.1, 0.13, 0.15, 0.18])
    expected = (0.5 * m * (vc**2).sum(-1) + 0.5 * (m * r**2 / 2) * w**2).sum(-1)
    torch.testing.assert_close(kinetic_energy(inertia, v), expected, atol=1e-12, rtol=1e-12)
    D = dense(M, 2)
    torch.testing.assert_close(
        0.5 * torch.einsum("bi,ij,bj->b", v.reshape(2, -1), D, v.reshape(2, -1)), expected, atol=1e-12, rtol=1e-12
    )


def test_gyroscope_inertia_about_pivot():
    """The top's kinetic energy from 4 points equals ½ ωᵀ I_pivot ω with I_pivot = I_com + m |c|² (⊥ axes)."""
    from diffcontact.systems.gyroscope import gyro_points

    task = build_task("Gyro")
    com = torch.tensor([0.0, 0.0, 0.5])
    zero = torch.zeros(1)
    x, v = gyro_points(com, zero, zero, zero, torch.tensor([0.7]), torch.tensor([0.2]), torch.tensor([3.0]))
    # at zero angles body = world axes; body rates = (θ̇, 0, φ̇ + ψ̇)
    w = torch.tensor([0.2, 0.0, 3.7])
    m = 0.1
    I_com = torch.tensor([m * (0.24 + 0.04), m * (0.24 + 0.04), m * (0.24 + 0.24)])
    I_piv = I_com + m * 0.25 * torch.tensor([1.0, 1.0, 0.0])
    assert kinetic_energy(task.params.inertia, v).item() == pytest.approx(0.5 * (I_piv * w * w).sum().item(), rel=1e-12)


@pytest.mark.parametrize("name", ["CP3", "BD5", "Gyro", "Rope"])
def test_hamiltonian_field_equals_lagrangian(name):
    task = build_task(name)
    s = task.sample(4, seed=5)
    cons, params = task.system.constraints, task.params
    xd, vd = lagrangian_field(cons, params, s.x, s.v)
    xd2, pd = hamiltonian_field(cons, params, s.x, momentum(params, s.v))
    M, _ = body_blocks(params.inertia)
    torch.testing.assert_close(xd2, xd, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(pd, apply_blocks(M, vd), atol=1e-9, rtol=1e-9)


def test_hamiltonian_rollout_with_contacts_matches_lagrangian():
    """Off the constraint manifold (inside an RK4 step) the two fields differ, so rollouts agree up to the
    integration error: run at dt/8 where that error is ~1e-9."""
    task = build_task("Gyro", overrides={"walls": {"planes": [[0.0, 1.0, 0.0, 0.2]]}})  # a closer wall
    s = task.sample(8, seed=4)
    dt = task.dt / 8
    with torch.no_grad():
        xl, vl, hl = simulator_for(task).rollout(s, task.params, dt, 120)
        xh, vh, hh = simulator_for(task, dynamics="hamiltonian").rollout(s, task.params, dt, 120)
    assert hl.any()
    assert torch.equal(hl, hh)
    torch.testing.assert_close(xh, xl, atol=1e-8, rtol=0)
    torch.testing.assert_close(vh, vl, atol=1e-7, rtol=0)


@pytest.mark.slow
@pytest.mark.parametrize("name, horizon", [("CP3-e", 0.2), ("Gyro-e", 0.2), ("Rope", 0.05)])
def test_rk4_empirical_order_is_four(name, horizon):
    """Between impacts (no contact on the interval) the global error of the 3/8-rule RK4 step scales as dt⁴."""
    task = build_task(name)
    sim = simulator_for(task)
    s = task.sample(4, seed=7)

    def run(n):
        x, v = s.x, s.v
        for _ in range(n):
            x, v = sim.flow(task.params, x, v, horizon / n)
        return torch.cat([x.flatten(1), v.flatten(1)], 1)

    with torch.no_grad():
        ref = run(512)
        errs = [(run(n) - ref).norm().item() for n in (8, 16, 32)]
    orders = [math.log2(errs[i] / errs[i + 1]) for i in range(2)]
    assert all(3.6 < p < 4.4 for p in orders), (errs, orders)


@pytest.mark.parametrize("name", ["CP3", "BD5", "Gyro"])
def test_contact_impulses_keep_equality_constraints(name):
    """M̂⁻¹ maps impulses into the constraint tangent space: J_E v⁺ = 0 to rounding after every contact."""
    task = build_task(name)
    sim = simulator_for(task)
    s = task.sample(64, seed=8)
    hits = 0
    state = s
    with torch.no_grad():
        for _ in range(40):
            x1, v1 = sim.flow(task.params, state.x, state.v, task.dt)
            cons = task.system.constraints
            before = (cons.jac(x1) @ v1.reshape(64, -1, 1)).abs().amax((1, 2))
            v2, hit = sim.contact_model(task.system, task.params, x1, v1, task.dt)
            after = (cons.jac(x1) @ v2.reshape(64, -1, 1)).abs().amax((1, 2))
            assert ((after - before)[hit].abs() < 1e-11).all()
            hits += int(hit.sum())
            state = State(x1, v2)
    assert hits > 0


def test_equality_constraint_drift_over_100_steps():
    """With RK4 accurate on the time scale (dt/8 for the gyroscope's spin of ~10 rad/s), |Φ| stays below 1e-6
    over 100 steps through impacts (a raised ground and a closer wall make them happen)."""
    cases = [
        ("Gyro-e", {"walls": {"planes": [[0.0, 1.0, 0.0, 0.2]]}}, 8),
        ("CP3", {"walls": {"lines": [[0.0, 1.0, 0.6]]}}, 4),
    ]
    for name, overrides, div in cases:
        task = build_task(name, overrides=overrides)
        s = task.sample(16, seed=9)
        with torch.no_grad():
            x, _, hit = simulator_for(task).rollout(s, task.params, task.dt / div, 101)
        assert hit.any(), name
        drift = task.system.constraints.phi(x.flatten(0, 1)).abs().max().item()
        assert drift < DRIFT_TOL, (name, drift)


@pytest.mark.parametrize("task_name", ["BD5", "Gyro", "Rope", "CP3"])
def test_effective_inverse_inertia_equals_paper_eq_8_and_is_psd_for_extreme_moments(task_name):
    """M̂⁻¹J_Cᵀ and A against Eq. 8 with dense inverses (float64); with moments of e^±8 per unit mass in float32,
    A (factored as Z Zᵀ) stays PSD to its rounding, where the difference of Eq. 8 did not (−0.4 %)."""
    from diffcontact.contact.effective_mass import effective_inverse_inertia
    from diffcontact.dynamics.inertia import inverse_factor_blocks
    from diffcontact.state import Inertia

    task = build_task(task_name)
    system, inertia = task.system, task.params.inertia
    x = task.sample(6, seed=0).x
    gen = torch.Generator().manual_seed(1)
    Jc = torch.randn(6, 4, x.shape[1] * x.shape[2], generator=gen, dtype=torch.float64)
    L = inverse_factor_blocks(inertia)
    _, Minv = body_blocks(inertia)
    torch.testing.assert_close(L @ L.mT, Minv, atol=1e-12, rtol=1e-12)
    MhJt, A = effective_inverse_inertia(L, system.constraints, x, Jc)
    Mi = dense(Minv, system.d)
    if system.constraints.count:
        JE = system.constraints.jac(x)
        Mi = Mi - Mi @ JE.mT @ torch.linalg.inv(JE @ Mi @ JE.mT) @ JE @ Mi
    torch.testing.assert_close(MhJt, Mi @ Jc.mT, atol=1e-10, rtol=1e-9)
    torch.testing.assert_close(A, Jc @ Mi @ Jc.mT, atol=1e-10, rtol=1e-9)
    if inertia.moments.numel():
        for log_moment in (-8.0, 8.0):
            extreme = Inertia(inertia.masses.float(), torch.full_like(inertia.moments, log_moment).exp().float())
            _, A32 = effective_inverse_inertia(
                inverse_factor_blocks(extreme), system.constraints, x.float(), Jc.float()
            )
            evals = torch.linalg.eigvalsh(A32.double())
            ref = A32.diagonal(dim1=-2, dim2=-1).amax(-1).double()
            assert (evals[:, 0] >= -1e-6 * ref).all(), (evals[:, 0] / ref).min()


@pytest.mark.parametrize("name", ["BD1", "CP3", "Gyro", "Rope"])
def test_replacing_the_inertia_moves_gravity_with_it(name):
    """The potential reads the masses of the Params holding it: with every body's mass scaled by its own s_b and
    nothing else replaced, the force changes by the gravity on the added mass, (s_b − 1) m_b g per body (the
    centre point carries a body's gravity), and no other term of the potential (the rope's springs) changes."""
    from diffcontact.dynamics.lagrangian import potential_force
    from diffcontact.state import Inertia

    task = build_task(name)
    p, sys = task.params, task.system
    scale = torch.linspace(0.5, 2.0, sys.n_bodies, dtype=torch.float64)
    heavier = p.replace(inertia=Inertia(p.inertia.masses * scale, p.inertia.moments))
    x = task.sample(3, seed=2).x
    g = task.config.section("potential").number("gravity", 9.81)
    down = -torch.eye(sys.d, dtype=torch.float64)[-1]
    added = torch.zeros(sys.n_points, sys.d, dtype=torch.float64)
    added[:: sys.points_per_body] = ((scale - 1) * p.inertia.masses * g)[:, None] * down
    assert added.abs().max() > 0.1
    change = potential_force(heavier, x) - potential_force(p, x)
    torch.testing.assert_close(change, added.expand_as(x), rtol=0.0, atol=1e-14)  # (measured: 2e-16)
