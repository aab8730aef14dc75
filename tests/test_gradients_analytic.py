"""Gradients through impacts against closed forms (float64): two balls of different masses (head-on and
at an angle), a ball bouncing under gravity with e < 1 (apex after n bounces), a spinning disk hitting the ground
with friction (sticking and sliding).

Each case simulates with the time of impact (TOI) and compares the final state and its Jacobian w.r.t. initial
positions, velocities, μ and e (autograd through the Simulator) with the closed form (autograd through the
formula, an independent code path), at several dt. The published scheme is run on the same cases: its error
is documented (asserted to be there), not asserted away.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch.autograd.functional import jacobian

from diffcontact.config import task_from_dict
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems import build_task
from diffcontact.systems.bouncing import disk_points

F64 = torch.float64
STATE_TOL = 1e-6  # final state within 1e-6 of the closed form with TOI
GRAD_TOL = 1e-4  # and its gradient within 1e-4
G = 9.81
DTS = [0.01, 0.007]


def task_of(kind="point", masses=(1.0,), radii=(0.1,), walls=(), mu=0.0, cor=1.0, gravity=0.0, dt=0.01):
    raw = {
        "task": {"name": "analytic", "system": "bouncing", "dt": dt, "frames": 10},
        "bodies": {"kind": kind, "masses": list(masses), "radii": list(radii)},
        "walls": {"lines": [list(w) for w in walls]},
        "potential": {"gravity": gravity},
        "contact": {"mu": [mu], "cor": [cor]},
    }
    return build_task(task_from_dict(raw))


def run(task, x0, v0, steps, toi, mu=None, e=None):
    """Positions and velocities (steps + 1, P, d) of one trajectory; μ, e (scalars) replace the task's."""
    params = task.params
    if mu is not None:
        params = params.replace(mu=mu.expand(task.system.n_slots))
    if e is not None:
        params = params.replace(e=e.expand(task.system.n_slots))
    sim = simulator_for(task, time_of_impact=toi)
    xs, vs, hit = sim.rollout(State(x0[None], v0[None]), params, task.dt, steps + 1)
    assert bool(hit.any()), "the case must contain an impact"
    return xs[0], vs[0]


def compare(sim_fn, closed_fn, theta, toi=True):
    """(max |state error|, max |Jacobian error|) of sim_fn against closed_fn at theta."""
    got, want = sim_fn(theta), closed_fn(theta)
    J_got, J_want = jacobian(sim_fn, theta), jacobian(closed_fn, theta)
    assert torch.isfinite(J_got).all()
    return (got - want).abs().max().item(), (J_got - J_want).abs().max().item()


# --- two balls -------------------------------------------------------------------------------------------------

M, R = (1.0, 3.0), (0.1, 0.15)
HEAD_ON = [0.2, 0.5, 0.8, 0.5, 1.0, 0.0, -0.5, 0.0, 0.7]  # x1, x2, v1, v2 (2D each), e
OBLIQUE = [0.2, 0.5, 0.8, 0.62, 1.0, 0.1, -0.5, 0.0, 0.7]


def two_balls_closed(theta: torch.Tensor, T: float) -> torch.Tensor:
    """Final positions (4,) of two frictionless balls colliding once (Poisson e = theta[8]) at time t_c."""
    x1, x2, v1, v2, e = theta[0:2], theta[2:4], theta[4:6], theta[6:8], theta[8]
    p, w, rr = x2 - x1, v2 - v1, R[0] + R[1]
    pw, ww = p @ w, w @ w
    t_c = (-pw - torch.sqrt(pw**2 - ww * (p @ p - rr**2))) / ww
    n = (p + w * t_c) / rr
    j = -(1 + e) * (w @ n) / (1 / M[0] + 1 / M[1])
    y1 = x1 + v1 * t_c + (v1 - j * n / M[0]) * (T - t_c)
    y2 = x2 + v2 * t_c + (v2 + j * n / M[1]) * (T - t_c)
    return torch.cat([y1, y2])


def two_balls_sim(dt: float, steps: int, toi: bool):
    task = task_of(masses=M, radii=R, dt=dt)

    def final(theta):
        xs, _ = run(task, theta[0:4].reshape(2, 2), theta[4:8].reshape(2, 2), steps, toi, e=theta[8])
        return xs[-1].flatten()

    return final


@pytest.mark.parametrize("dt", DTS)
@pytest.mark.parametrize("case", [HEAD_ON, OBLIQUE], ids=["head-on", "oblique"])
def test_two_balls_of_different_masses(case, dt):
    steps = round(0.5 / dt)
    theta = torch.tensor(case, dtype=F64)
    err_x, err_J = compare(two_balls_sim(dt, steps, True), lambda th: two_balls_closed(th, steps * dt), theta)
    assert err_x < STATE_TOL and err_J < GRAD_TOL


# --- a ball bouncing under gravity -----------------------------------------------------------------------------


def bounce_closed(theta: torch.Tensor, n: int) -> torch.Tensor:
    """Apex height (m) of a ball (r = 0.1, ground y = 0) after n bounces from height y0, vertical speed vy0,
    restitution e: r + (e^n u)²/(2g) with u = √(vy0² + 2g(y0 − r)) the first impact speed."""
    y0, vy0, e = theta
    u = torch.sqrt(vy0**2 + 2 * G * (y0 - 0.1))
    return 0.1 + (e**n * u) ** 2 / (2 * G)


def apex_frame(theta: torch.Tensor, n: int, dt: float) -> int:
    """A frame between the n-th and the (n+1)-th bounce (the one nearest the apex)."""
    y0, vy0, e = theta.tolist()
    u = math.sqrt(vy0**2 + 2 * G * (y0 - 0.1))
    t = (vy0 + u) / G + sum(2 * e**k * u / G for k in range(1, n)) + e**n * u / G
    return round(t / dt)


def bounce_sim(dt: float, frame: int, toi: bool):
    task = task_of(walls=((0.0, 1.0, 0.0),), cor=0.8, gravity=G, dt=dt)

    def apex(theta):
        y0, vy0, e = theta
        x0 = torch.stack([torch.full_like(y0, 0.2), y0])[None]
        v0 = torch.stack([torch.full_like(y0, 0.3), vy0])[None]
        xs, vs = run(task, x0, v0, frame, toi, e=e)
        y, vy = xs[-1, 0, 1], vs[-1, 0, 1]
        return (y + vy**2 / (2 * G))[None]  # the ballistic apex of the last state (RK4 is exact in flight)

    return apex


@pytest.mark.parametrize("dt", DTS)
@pytest.mark.parametrize("n", [1, 3])
def test_bouncing_ball_apex_after_n_bounces(n, dt):
    theta = torch.tensor([0.5, 0.4, 0.8], dtype=F64)  # y0 (m), vy0 (m/s), e
    frame = apex_frame(theta, n, dt)
    err_x, err_J = compare(bounce_sim(dt, frame, True), lambda th: bounce_closed(th, n)[None], theta)
    assert err_x < STATE_TOL and err_J < GRAD_TOL


# --- a spinning disk hitting the ground with friction ----------------------------------------------------------

RD, MD = 0.1, 0.5  # disk radius (m) and mass (kg); moment m r²/2


def _phase(un, ut, lower, mu):
    """One phase of the model's maximum-dissipation impact of a disk on the ground (A = diag(1/m, 3/m)):
    min ½fᵀAf + fᵀu over |f_t| <= μ f_n, f_n >= lower. Sticks if −m u_t/3 is in the cone, else slides on its
    edge with f_n the minimiser of the parabola along it (the convex model's normal–friction coupling)."""
    fn, ft = torch.clamp_min(-MD * un, lower), -MD * ut / 3
    if ft.abs() <= mu * fn:
        return fn, ft
    fn = torch.clamp_min(MD * (-un + mu * ut.abs()) / (1 + 3 * mu**2), lower)
    return fn, -mu * fn * torch.sign(ut)


def disk_closed(theta: torch.Tensor, T: float) -> torch.Tensor:
    """Final centre (2,), angle and velocities (vx, vy, ω) of a disk (angle 0 at the start, moment m r²/2)
    dropped on the ground y = 0 under gravity; theta = (y0, vx0, vy0, ω0, μ, e).

    One impact at t_c (impact speed u): compression then restitution (f_n >= e f_c,n), see ``_phase``; the
    contact point's slip is vx + ω r, the impulse (f_t, f_n) changes vx by f_t/m, vy by f_n/m, ω by r f_t/I.
    """
    y0, vx, vy, w, mu, e = theta
    u = torch.sqrt(vy**2 + 2 * G * (y0 - RD))
    t_c = (vy + u) / G
    fcn, fct = _phase(-u, vx + w * RD, torch.zeros_like(u), mu)
    un, ut = -u + fcn / MD, vx + w * RD + 3 * fct / MD
    frn, frt = _phase(un, ut, e * fcn, mu)
    fn, ft = fcn + frn, fct + frt
    vx1, vy1, w1 = vx + ft / MD, -u + fn / MD, w + RD * ft / (MD * RD**2 / 2)
    tau = T - t_c
    xc = 0.5 + vx * t_c + vx1 * tau
    yc = RD + vy1 * tau - G * tau**2 / 2
    return torch.stack([xc, yc, w * t_c + w1 * tau, vx1, vy1 - G * tau, w1])


def disk_sim(dt: float, steps: int, toi: bool):
    task = task_of(kind="disk", masses=(MD,), radii=(RD,), walls=((0.0, 1.0, 0.0),), gravity=G, dt=dt)

    def final(theta):
        y0, vx, vy, w, mu, e = theta
        centre = torch.stack([torch.full_like(y0, 0.5), y0])[None, None]
        x0, v0 = disk_points(centre, torch.zeros_like(y0)[None, None], torch.stack([vx, vy])[None, None], w[None, None])
        xs, vs = run(task, x0[0], v0[0], steps, toi, mu=mu, e=e)
        c, e1, dc, de1 = xs[-1, 0], xs[-1, 1] - xs[-1, 0], vs[-1, 0], vs[-1, 1] - vs[-1, 0]
        angle = torch.atan2(e1[1], e1[0])
        omega = e1[0] * de1[1] - e1[1] * de1[0]
        return torch.stack([c[0], c[1], angle, dc[0], dc[1], omega])

    return final


STICK = [0.2, 0.3, -0.5, 2.0, 0.5, 0.6]  # y0, vx0, vy0, ω0, μ, e: |s| = 0.5 < 3 μ (1+e) u
SLIDE = [0.2, 1.5, -0.5, 5.0, 0.1, 0.6]  # |s| = 2.0 > 3 μ (1+e) u


@pytest.mark.parametrize("dt", DTS)
@pytest.mark.parametrize("case", [STICK, SLIDE], ids=["sticking", "sliding"])
def test_spinning_disk_hits_the_ground_with_friction(case, dt):
    theta = torch.tensor(case, dtype=F64)
    steps = round(0.25 / dt)
    err_x, err_J = compare(disk_sim(dt, steps, True), lambda th: disk_closed(th, steps * dt), theta)
    assert err_x < STATE_TOL and err_J < GRAD_TOL


# --- a chain pendulum bob hitting the ground -------------------------------------------------------------------

LP, RP, GROUND = 1.0, 0.1, 0.9  # link length, bob radius, ground y = −0.9 (m)


def pendulum_closed(theta: torch.Tensor, T: float) -> torch.Tensor:
    """Angle (from the downward vertical) at T of a one-link chain pendulum without gravity (uniform rotation)
    from angle q0 at rate w toward the ground, frictionless impact with restitution e: the bob touches at
    cos q_c = (0.9 − r)/l, then turns back at −e w. (Gravity-free: the rotation is the closed form.)"""
    q0, w, e = theta
    q_c = torch.arccos(torch.tensor((GROUND - RP) / LP, dtype=F64))
    t_c = (q_c - q0) / w
    return (q_c - e * w * (T - t_c))[None]


def pendulum_sim(dt: float, steps: int, toi: bool):
    from diffcontact.systems.pendulum import chain_points

    raw = {
        "task": {"name": "analytic-pendulum", "system": "chain_pendulum", "dt": dt, "frames": 10},
        "bodies": {"masses": [0.3], "radii": [RP]},
        "pendulum": {"lengths": [LP], "pivot": [0.0, 0.0]},
        "walls": {"lines": [[0.0, 1.0, GROUND]]},
        "potential": {"gravity": 0.0},
        "contact": {"mu": [0.0], "cor": [0.6]},
    }
    task = build_task(task_from_dict(raw))
    pivot, ell = torch.zeros(2, dtype=F64), torch.tensor([LP], dtype=F64)

    def final(theta):
        q0, w, e = theta
        x0, v0 = chain_points(pivot, ell, q0[None, None], w[None, None])
        xs, _ = run(task, x0[0], v0[0], steps, toi, e=e)
        return torch.atan2(xs[-1, 0, 0], -xs[-1, 0, 1])[None]

    return final


@pytest.mark.parametrize("dt", DTS)
def test_chain_pendulum_bob_hits_the_ground(dt):
    theta = torch.tensor([1.2, -2.0, 0.6], dtype=F64)  # q0 (rad), w (rad/s), e
    steps = round(0.5 / dt)
    err_x, err_J = compare(pendulum_sim(dt, steps, True), lambda th: pendulum_closed(th, steps * dt), theta)
    assert err_x < STATE_TOL and err_J < GRAD_TOL


# --- the published scheme on the same cases --------------------------------------------------------------------

PUBLISHED = {  # case: (simulated, closed form, theta, measured (state error, Jacobian error) at dt = 0.01)
    "head-on": (two_balls_sim(0.01, 50, False), lambda th: two_balls_closed(th, 0.5), HEAD_ON, (1.3e-2, 1.27)),
    "oblique": (two_balls_sim(0.01, 50, False), lambda th: two_balls_closed(th, 0.5), OBLIQUE, (9.3e-3, 1.51)),
    "bounce-3": (bounce_sim(0.01, 131, False), lambda th: bounce_closed(th, 3)[None], [0.5, 0.4, 0.8], (1.0e-2, 0.83)),
    "disk-slide": (disk_sim(0.01, 25, False), lambda th: disk_closed(th, 0.25), SLIDE, (0.29, 20.5)),
    "pendulum": (pendulum_sim(0.01, 50, False), lambda th: pendulum_closed(th, 0.5), [1.2, -2.0, 0.6], (5.6e-3, 1.6)),
}


@pytest.mark.parametrize("case", sorted(PUBLISHED))
def test_published_scheme_error_is_documented(case):
    """The published scheme (contact resolved at the end of the step) on the same cases at dt = 0.01: the
    measured errors (docs/gradients.md) are reproduced to 10 %. Its Jacobian error does not shrink with dt
    (1.27 at dt = 0.01 and at dt = 0.001 head-on): the impact time is missing from the derivative."""
    sim_fn, closed_fn, theta, (want_x, want_J) = PUBLISHED[case]
    err_x, err_J = compare(sim_fn, closed_fn, torch.tensor(theta, dtype=F64))
    assert err_x == pytest.approx(want_x, rel=0.1) and err_J == pytest.approx(want_J, rel=0.1)
