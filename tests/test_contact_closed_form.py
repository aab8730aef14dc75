"""Closed-form impacts (float64): wall bounce, head-on exchange, frictional disk impact, COR = 0, CM vs CMr."""

from __future__ import annotations

import math

import pytest
import torch

from diffcontact.config import task_from_dict
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems import build_task

SOLVER_TOL = 1e-8  # the cone-QP solver converges to a KKT residual of ~1e-10
BOX = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 1.0], [0.0, -1.0, 1.0]]


def bouncing(
    kind="point", masses=(1.0,), radii=(0.1,), mu=(0.0,), cor=(1.0,), gravity=0.0, comp=0.125, walls=BOX, dt=0.01
):
    raw = {
        "task": {"name": "test", "system": "bouncing", "dt": dt, "frames": 10},
        "bodies": {"kind": kind, "masses": list(masses), "radii": list(radii)},
        "walls": {"lines": walls},
        "potential": {"gravity": gravity},
        "contact": {"mu": list(mu), "cor": list(cor), "compensation": comp, "time_of_impact": False},
    }
    return build_task(task_from_dict(raw))


def contact(task, x, v, reg=0.0):
    sim = simulator_for(task, reg=reg)
    x = torch.as_tensor(x, dtype=torch.float64)[None]
    v = torch.as_tensor(v, dtype=torch.float64)[None]
    v1, hit = sim.contact_model(task.system, task.params, x, v, task.dt)
    return v1[0], bool(hit[0])


def test_ball_wall_leaves_with_e_times_normal_speed():
    e, depth, dt = 0.7, 0.005, 0.01
    task = bouncing(cor=(e,), dt=dt)
    v1, hit = contact(task, [[0.1 - depth, 0.5]], [[-1.0, 0.3]])
    assert hit
    # compensation target 1/8 depth/dt = 0.0625 < e * 1, so Poisson's bound decides
    torch.testing.assert_close(v1, torch.tensor([[e * 1.0, 0.3]], dtype=torch.float64), atol=SOLVER_TOL, rtol=0)


def test_equal_balls_head_on_elastic_exchange_velocities():
    task = bouncing(masses=(1.0, 1.0), radii=(0.1, 0.1), cor=(1.0,))
    v1, _ = contact(task, [[0.3, 0.5], [0.499, 0.5]], [[1.0, 0.25], [0.0, 0.0]])
    # normal (x) components exchange; the frictionless tangential (y) component is untouched
    torch.testing.assert_close(
        v1, torch.tensor([[0.0, 0.25], [1.0, 0.0]], dtype=torch.float64), atol=SOLVER_TOL, rtol=0
    )


def test_unequal_masses_conserve_momentum_and_follow_poisson():
    m1, m2, e = 0.05, 0.5, 0.6
    task = bouncing(masses=(m1, m2), radii=(0.05, 0.18), cor=(e,))
    f64 = torch.float64
    n = torch.tensor([0.6, 0.8], dtype=f64)
    c1 = torch.tensor([0.3, 0.4], dtype=f64)
    c2 = c1 + 0.2299 * n  # overlapping by 1e-4 along n
    u1, u2 = torch.tensor([1.0, 0.5], dtype=f64), torch.tensor([-0.2, 0.1], dtype=f64)
    v1, _ = contact(task, torch.stack([c1, c2]), torch.stack([u1, u2]))
    p0 = m1 * u1 + m2 * u2
    torch.testing.assert_close(m1 * v1[0] + m2 * v1[1], p0, atol=SOLVER_TOL, rtol=0)
    rel_in = ((u2 - u1) @ n).item()
    rel_out = ((v1[1] - v1[0]) @ n).item()
    assert rel_out == pytest.approx(-e * rel_in, abs=SOLVER_TOL)


def _disk_state(theta, centre, vel, omega):
    from diffcontact.systems.bouncing import disk_points

    x, v = disk_points(
        torch.tensor([[centre]], dtype=torch.float64),
        torch.tensor([[theta]], dtype=torch.float64),
        torch.tensor([[vel]], dtype=torch.float64),
        torch.tensor([[omega]], dtype=torch.float64),
    )
    return x[0], v[0]


def _oracle_disk_floor(m, r, vn, ut, mu, e):
    """Two-phase maximum-dissipation impact of a disk (I = m r²/2) on a floor, zero compensation target.

    In the contact frame A = diag(1/m, 3/m) (no normal–tangent coupling for a disk on a plane). Each phase
    minimises ½fᵀAf + fᵀu over the Coulomb cone |f_t| <= μ f_n (restitution also f_n >= e f_cn): either the
    stick solution (f_t = −m u_t/3) is inside the cone, or the impulse slides on the cone's edge.
    """

    def phase(un, ut, lower):
        fn = max(lower, -m * un)  # stick: normal and tangent decouple
        ft = -m * ut / 3
        if abs(ft) <= mu * fn + 1e-15:
            return fn, ft
        s = math.copysign(1.0, ut)  # slide: f_t = −μ f_n s, minimise a parabola in f_n
        fn = max(lower, m * (-un + mu * abs(ut)) / (1 + 3 * mu * mu))
        return fn, -mu * fn * s

    fcn, fct = phase(vn, ut, 0.0)
    un, ut2 = vn + fcn / m, ut + 3 * fct / m
    frn, frt = phase(un, ut2, e * fcn)
    return fcn + frn, fct + frt


@pytest.mark.parametrize("mu, regime", [(1.0, "stick"), (0.1, "slide")])
def test_frictional_disk_impact_spin_and_coulomb_regime(mu, regime):
    m, r, e = 1.0, 0.1, 0.5
    vx, vy, omega = 1.0, -1.0, 0.0
    task = bouncing(kind="disk", masses=(m,), radii=(r,), mu=(mu,), cor=(e,), comp=0.0)
    x, v = _disk_state(0.3, [0.5, r - 1e-4], [vx, vy], omega)
    v1, hit = contact(task, x, v)
    assert hit
    ut = vx + omega * r  # floor frame: tangential speed of the contact point along +x
    fn, ft = _oracle_disk_floor(m, r, vy, ut, mu, e)
    I = m * r * r / 2
    e1, de1 = x[1] - x[0], v1[1] - v1[0]
    omega1 = (e1[0] * de1[1] - e1[1] * de1[0]).item()
    tol = 1e-12  # (m/s and rad/s; measured: at most 8e-15)
    assert v1[0, 0].item() == pytest.approx(vx + ft / m, abs=tol)
    assert v1[0, 1].item() == pytest.approx(vy + fn / m, abs=tol)
    assert omega1 == pytest.approx(omega + r * ft / I, abs=tol)
    slip = v1[0, 0].item() + omega1 * r
    if regime == "stick":
        assert abs(slip) < tol  # rolls without slipping after the impact
    else:
        assert slip > 0.1 and abs(ft) == pytest.approx(mu * fn, rel=tol)  # still sliding, on the cone edge


def test_cor_zero_no_rebound_and_compensation_target():
    depth, dt, comp = 0.004, 0.01, 0.125
    task0 = bouncing(cor=(0.0,), comp=0.0, dt=dt)
    v1, _ = contact(task0, [[0.5, 0.1 - depth]], [[0.2, -1.5]])
    torch.testing.assert_close(v1, torch.tensor([[0.2, 0.0]], dtype=torch.float64), atol=SOLVER_TOL, rtol=0)
    task = bouncing(cor=(0.0,), comp=comp, dt=dt)
    v1, _ = contact(task, [[0.5, 0.1 - depth]], [[0.2, -1.5]])
    # the only normal velocity left is the compensation target of paper Suppl. F: comp · depth / dt
    assert v1[0, 1].item() == pytest.approx(comp * depth / dt, abs=SOLVER_TOL)


def test_cor_zero_drop_does_not_bounce():
    task = bouncing(cor=(0.0,), gravity=9.81, walls=[[0.0, 1.0, 0.0]])
    sim = simulator_for(task)
    s0 = State(torch.tensor([[[0.5, 0.3]]], dtype=torch.float64), torch.zeros(1, 1, 2, dtype=torch.float64))
    with torch.no_grad():
        x, _, hit = sim.rollout(s0, task.params, task.dt, 100)
    first = int(torch.nonzero(hit[0])[0])
    height = x[0, first:, 0, 1] - 0.1
    depth0 = -height[0].item()
    assert depth0 > 0
    assert height.max().item() < 0.05 * depth0 + 1e-12  # never lifts off (a COR=0 ball with 1-step fix would)
    assert height.min().item() >= -depth0 - 1e-12  # the penetration is not made worse


def _cmr_oracle(vn, lam, r):
    """Normal velocity after a frictionless e = 0 impact in CMr with one effective contact of inverse
    inertia λ: each phase leaves the fraction r/(λ + r) of the contact velocity, so v⁺ = v⁻ (r/(λ + r))²
    (CM, r = 0, stops exactly)."""
    return vn * (r / (lam + r)) ** 2


@pytest.mark.parametrize("mass", [0.001, 1.0])
def test_cm_and_cmr_single_contact(mass):
    task = bouncing(masses=(mass,), cor=(0.0,), mu=(0.0,), comp=0.0)
    x, v = [[0.099, 0.5]], [[-1.0, 0.4]]
    v_cm, _ = contact(task, x, v)
    v_cmr, _ = contact(task, x, v, reg=0.01)
    assert v_cm[0, 0].item() == pytest.approx(0.0, abs=SOLVER_TOL)
    assert v_cmr[0, 0].item() == pytest.approx(_cmr_oracle(-1.0, 1 / mass, 0.01), abs=SOLVER_TOL)
    if mass < 0.01:  # well conditioned: λ = 1000 >> r, CM and CMr agree
        assert (v_cmr - v_cm).abs().max().item() < 1e-9


def test_cm_and_cmr_on_singular_a():
    # a ball of radius 0.5001 squeezed between the walls x = 0 and x = 1: normals (1, 0) and (-1, 0) make
    # A = [[1, -1], [-1, 1]] / m singular. CM stops the ball exactly; CMr leaves -(r/(1 + r))^2, as derived
    # by hand (the second normal is inactive at the optimum, so the effective λ is 1/m = 1).
    task = bouncing(
        masses=(1.0,), radii=(0.5001,), cor=(0.0,), mu=(0.0,), comp=0.0, walls=[[1.0, 0.0, 0.0], [-1.0, 0.0, 1.0]]
    )
    x, v = [[0.5, 0.5]], [[-1.0, 0.3]]
    v_cm, _ = contact(task, x, v)
    assert v_cm[0, 0].item() == pytest.approx(0.0, abs=SOLVER_TOL)
    for r in (1e-2, 1e-1):
        v_cmr, _ = contact(task, x, v, reg=r)
        assert v_cmr[0, 0].item() == pytest.approx(_cmr_oracle(-1.0, 1.0, r), abs=SOLVER_TOL)
        assert v_cmr[0, 1].item() == pytest.approx(0.3, abs=SOLVER_TOL)
