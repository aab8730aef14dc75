"""Time of impact (float64): the issue-15 ball–wall case, the scheme switch and task keys, edge cases."""

from __future__ import annotations

import pytest
import torch

from diffcontact.config import task_from_dict
from diffcontact.errors import ConfigError
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems import BENCHMARK_TASKS, build_task

F64 = torch.float64
STATE_TOL = 1e-6  # final state within 1e-6 of the closed form with TOI
GRAD_TOL = 1e-4  # and its gradient within 1e-4


def balls(masses=(1.0,), radii=(0.1,), walls=((-1.0, 0.0, 1.0),), mu=0.0, cor=1.0, gravity=0.0, dt=0.01, **extra):
    raw = {
        "task": {"name": "t", "system": "bouncing", "dt": dt, "frames": 10},
        "bodies": {"kind": "point", "masses": list(masses), "radii": list(radii)},
        "walls": {"lines": [list(w) for w in walls]},
        "potential": {"gravity": gravity},
        "contact": {"mu": [mu], "cor": [cor], **extra},
    }
    return build_task(task_from_dict(raw))


def final_x(task, x0, v0, frames, toi, dynamics="lagrangian"):
    """x at the last of ``frames`` frames (B, P, d) of a rollout from x0, v0 (P, d) (differentiable)."""
    xs, _, _ = simulator_for(task, dynamics, time_of_impact=toi).rollout(
        State(x0[None], v0[None]), task.params, task.dt, frames
    )
    return xs[:, -1]


def ball_wall(x0: float, speed: float, dt: float, toi: bool, steps: int = 100, dynamics: str = "lagrangian"):
    """The closed-form case: m = 1, r = 0.1, wall x = 1, e = 1, T = steps·dt: x(T) and ∂x(T)/∂(x0, v)."""
    task = balls(dt=dt)
    p = torch.tensor([x0, speed], dtype=F64, requires_grad=True)
    zero, half = torch.zeros((), dtype=F64), torch.tensor(0.5, dtype=F64)
    x0_, v0_ = torch.stack([p[0], half])[None], torch.stack([p[1], zero])[None]
    xT = final_x(task, x0_, v0_, steps + 1, toi, dynamics)[0, 0, 0]
    (grad,) = torch.autograd.grad(xT, p)
    return xT.item(), grad.tolist()


@pytest.mark.parametrize("dt, dynamics", [(0.01, "lagrangian"), (0.007, "lagrangian"), (0.01, "hamiltonian")])
@pytest.mark.parametrize("x0", [0.3, 0.303])  # 0.3, dt = 0.01: the impact falls on a step boundary (t = 0.6 s)
def test_ball_wall_time_of_impact_matches_the_closed_form(x0, dt, dynamics):
    xT, grad = ball_wall(x0, 1.0, dt, toi=True, dynamics=dynamics)
    assert xT == pytest.approx(2 * 0.9 - (x0 + 100 * dt), abs=STATE_TOL)
    assert grad == pytest.approx([-1.0, -100 * dt], abs=GRAD_TOL)


def test_ball_wall_published_scheme_has_the_documented_gradient_error():
    """The published scheme (no time of impact): x0 = 0.3 gives x(T) = 0.5 and gradient (+1, +0.2)
    instead of (−1, −1); x0 = 0.303 gives x(T) = 0.503 (closed form 0.497) and the same gradient."""
    xT, grad = ball_wall(0.3, 1.0, 0.01, toi=False)
    assert xT == pytest.approx(0.5, abs=1e-9)
    assert grad == pytest.approx([1.0, 0.2], abs=1e-9)
    xT, grad = ball_wall(0.303, 1.0, 0.01, toi=False)
    assert xT == pytest.approx(0.503, abs=1e-9)  # a position error of 2 (x0 − 0.3): the impact's timing is lost
    assert grad == pytest.approx([1.0, 0.2], abs=1e-9)


def test_one_toi_step_passes_gradcheck():
    """One step with an impact mid-step (ball and wall, e = 0.7, μ = 0.3, gravity): gradcheck in (x, v, e, μ)."""
    task = balls(walls=((0.0, 1.0, 0.0),), mu=0.3, cor=0.7, gravity=9.81)
    sim = simulator_for(task, time_of_impact=True)

    def one_step(x, v, e, mu):
        params = task.params.replace(e=e.expand(1), mu=mu.expand(1))
        state, hit = sim.step(State(x, v), params, task.dt)
        assert bool(hit.all())
        return state.x, state.v

    x = torch.tensor([[[0.3, 0.104]]], dtype=F64, requires_grad=True)
    v = torch.tensor([[[0.4, -1.0]]], dtype=F64, requires_grad=True)
    e = torch.tensor([0.7], dtype=F64, requires_grad=True)
    mu = torch.tensor([0.3], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(one_step, (x, v, e, mu), eps=1e-7, atol=1e-6)


def _step_grads(task, x, v, toi=True):
    x = torch.tensor(x, dtype=F64, requires_grad=True)
    v = torch.tensor(v, dtype=F64, requires_grad=True)
    state, hit = simulator_for(task, time_of_impact=toi).step(State(x[None], v[None]), task.params, task.dt)
    gx, gv = torch.autograd.grad((state.x.sum() + state.v.sum()), (x, v))
    return state, bool(hit[0]), gx, gv


def test_grazing_contact_gives_finite_gradients():
    """A ball touching the ground (gap 0) at rest under gravity: zero normal velocity at the contact."""
    task = balls(walls=((0.0, 1.0, 0.0),), cor=0.5, gravity=9.81)
    state, hit, gx, gv = _step_grads(task, [[0.5, 0.1]], [[0.3, 0.0]])
    assert hit and torch.isfinite(gx).all() and torch.isfinite(gv).all()
    assert state.v[0, 0, 1] >= -1e-9  # not left moving into the ground


def test_simultaneous_contacts_give_finite_gradients_and_the_corner_bounce():
    """A ball hitting two walls at once (a corner, e = 1, frictionless): both normal velocities reverse."""
    task = balls(walls=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)), cor=1.0)
    state, hit, gx, gv = _step_grads(task, [[0.105, 0.105]], [[-1.0, -1.0]])
    assert hit and torch.isfinite(gx).all() and torch.isfinite(gv).all()
    torch.testing.assert_close(state.v[0, 0], torch.tensor([1.0, 1.0], dtype=F64), atol=1e-8, rtol=0)
    torch.testing.assert_close(state.x[0, 0], torch.tensor([0.105, 0.105], dtype=F64), atol=1e-8, rtol=0)


def test_contact_exactly_at_a_step_boundary_is_resolved_at_the_start_of_the_next_step():
    task = balls(cor=1.0)
    state, hit, gx, gv = _step_grads(task, [[0.9, 0.5]], [[1.0, 0.0]])  # gap 0 (−3e-17 by rounding), approaching
    assert hit and torch.isfinite(gx).all() and torch.isfinite(gv).all()
    assert state.x[0, 0, 0].item() == pytest.approx(0.89, abs=1e-12)
    assert state.v[0, 0, 0].item() == pytest.approx(-1.0, abs=1e-8)


def test_scheme_switch_and_task_keys():
    assert simulator_for(balls()).time_of_impact  # a task file without the key: TOI
    assert not simulator_for(balls(time_of_impact=False)).time_of_impact
    assert simulator_for(balls(time_of_impact=True), time_of_impact=False).time_of_impact is False
    for name in BENCHMARK_TASKS:  # the benchmark tasks keep the published scheme so their data stay comparable
        assert not build_task(name).system.stepping.time_of_impact, name
    assert build_task("Billiards").system.stepping.time_of_impact  # the control task: gradients through impacts
    with pytest.raises(ConfigError, match="contact.time_of_impact = 'yes' is not true or false"):
        balls(time_of_impact="yes")
    raw_task = {"name": "t", "system": "bouncing", "dt": 0.01, "frames": 10, "substeps": 0}
    with pytest.raises(ConfigError, match="task.substeps = 0 is smaller than 1"):
        bodies = {"kind": "point", "masses": [1], "radii": [0.1]}
        build_task(task_from_dict({"task": raw_task, "bodies": bodies, "contact": {"mu": [0.0], "cor": [1.0]}}))


def test_ball_in_a_corner_with_friction_gets_the_minimum_norm_impulse():
    """Time of impact, ambiguity (1): a ball hitting two perpendicular walls at once with friction has a singular A
    (4 contact rows, 2 degrees of freedom), so the compression impulse is not unique and the restitution bound
    e·f_n depends on the minimiser chosen. The solver returns the minimum-norm minimiser (solver/least_norm.py): checked
    here against Clarabel's minimum-norm minimiser (tests/solver_oracle.py), in the time-of-impact step."""
    np = pytest.importorskip("numpy")
    pytest.importorskip("cvxpy")
    from solver_oracle import clarabel_min_norm, clarabel_solve

    from diffcontact.solver import ContactSolver, solve_cone_qp

    calls = []

    def recording(A, q, mu, lower=None, active=None, **kw):
        f, info = solve_cone_qp(A, q, mu, lower, active, **kw)
        calls.append((A, q, mu, lower, f))
        return f, info

    task = balls(walls=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)), mu=0.5, cor=0.5)
    sim = simulator_for(task, solver=ContactSolver(backend=recording), time_of_impact=True)
    with torch.no_grad():
        sim.step(
            State(torch.tensor([[[0.105, 0.104]]], dtype=F64), torch.tensor([[[-1.0, -0.8]]], dtype=F64)),
            task.params,
            0.01,
        )
    A, q, mu, _, f = calls[0]  # the compression problem at the impact (both walls touch within tol)
    assert A.shape[-1] == 4 and torch.linalg.matrix_rank(A[0]).item() == 2
    args = (A[0].numpy(), q[0].numpy(), mu[0].numpy(), np.zeros(2), 2)
    f_min = clarabel_min_norm(*args, clarabel_solve(*args)[0])
    np.testing.assert_allclose(f[0].numpy(), f_min, atol=1e-6)


def test_rope_penetration_target_is_the_least_squares_projection_for_any_number_of_limits():
    """Time of impact, ambiguity (2), the rule kept (tasks/Rope.toml, docs/gradients.md): v*_C = J J⁺ v_d, the
    orthogonal projection of the wanted normal velocities onto what the limit rows can reach, for any number of
    active limits (the published code switches rule when more limits than points are active). Checked on Rope
    states with more than 10 active limits: Jᵀ(v_d − v*_C) = 0, and v*_C = v_d where J has full row rank."""
    task = build_task("Rope")
    sim = simulator_for(task)
    with torch.no_grad():
        x, _, _ = sim.rollout(task.sample(2, 0), task.params, task.dt, 30)
        flat = x.flatten(0, 1)
        count = (task.system.detector.gaps(flat) < 0).sum(1)
        pick = torch.argsort(count, descending=True)[:4]
        assert count[pick[0]] > task.system.n_points  # more active limits than the rope has points
        xs = flat[pick]
        contacts = task.system.detector.detect(xs)
        v_star = sim.contact_model.target_velocity(task.system.constraints, xs, contacts, task.dt)
    J = contacts.J
    v_d = -sim.contact_model.compensation * contacts.gap / task.dt  # the rope's rows are normal-only (dc = 1)
    residual = (J.mT @ (v_d - v_star)[..., None]).abs().max()
    assert residual < 1e-9 * (J.abs().max() * v_d.abs().max())
    full_row_rank = torch.linalg.matrix_rank(J) == contacts.active.sum(1)
    assert full_row_rank.any()
    torch.testing.assert_close(v_star[full_row_rank], v_d[full_row_rank], atol=1e-9, rtol=0)


def test_events_beyond_the_bound_are_resolved_at_the_end_of_the_step():
    """Two impacts in one step (walls x = 0 at s = 0.5 and y = 0 at s = 0.8): with max_events = 1 the second is
    left to the published rule (penetrating, velocity reversed at the end); with the default both are at TOI."""
    from dataclasses import replace

    task = balls(walls=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)), cor=1.0)
    state = State(torch.tensor([[[0.105, 0.104]]], dtype=F64), torch.tensor([[[-1.0, -0.5]]], dtype=F64))
    sim = simulator_for(task, time_of_impact=True)
    with torch.no_grad():
        full, _ = sim.step(state, task.params, task.dt)
        one, hit = replace(sim, max_events=1).step(state, task.params, task.dt)
    torch.testing.assert_close(full.x[0, 0], torch.tensor([0.105, 0.101], dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(full.v[0, 0], torch.tensor([1.0, 0.5], dtype=F64), atol=1e-8, rtol=0)
    assert bool(hit[0]) and one.x[0, 0, 0].item() == pytest.approx(0.105, abs=1e-9)
    assert one.x[0, 0, 1].item() == pytest.approx(0.099, abs=1e-9)  # penetrates by 1 mm: resolved at the end
    # reversed with e = 1: the Poisson bound f_n ≥ e·f_c,n binds, since the compensation target, 1/8 of depth/dt
    # = 0.0125 m/s, is below the 0.5 m/s it gives (this read > 0.5, true only by the solver's rounding, 2e-16)
    assert one.v[0, 0, 1].item() == pytest.approx(0.5, abs=1e-12)


@pytest.mark.parametrize("name", ["CP3-e", "Gyro-e"])
def test_toi_removes_impact_penetration_of_pendulum_bobs_and_the_disk_rim(name):
    """The generic TOI on the chain pendulum's bobs vs the ground and the gyroscope's disk rim vs its wall
    (elastic frictionless tasks: every contact is an impact): no penetration beyond tol, where the published
    scheme penetrates by centimetres, and the same energy error (RK4's)."""
    task = build_task(name)
    state = task.sample(4, 0)
    out = {}
    with torch.no_grad():
        for toi in (False, True):
            x, v, hit = simulator_for(task, time_of_impact=toi).rollout(state, task.params, task.dt, 100)
            E = task.system.energy(task.params, x.flatten(0, 1), v.flatten(0, 1)).reshape(4, 100)
            out[toi] = (task.system.detector.gaps(x.flatten(0, 1)).min().item(), (E - E[:, :1]).abs().max().item())
            assert hit.any()
    assert out[True][0] >= -1e-9 and out[False][0] < -1e-3
    assert out[True][1] == pytest.approx(out[False][1], rel=0.2)


def test_one_toi_step_of_the_disk_rim_passes_gradcheck():
    """Gyro-e: a step in which the disk's rim reaches its wall mid-step (gap +6.3 mm at the start, −3.5 mm at the
    end with the published scheme); gradcheck of the TOI step in (x, v) through the rim's closed-form gap."""
    task = build_task("Gyro-e")
    with torch.no_grad():
        x, v, _ = simulator_for(task).rollout(task.sample(4, 0), task.params, task.dt, 6)
        gaps = task.system.detector.gaps(x[0])[:, 0]
    assert gaps[4] > 0 > gaps[5]
    sim = simulator_for(task, time_of_impact=True)

    def one_step(xx, vv):
        state, hit = sim.step(State(xx, vv), task.params, task.dt)
        assert bool(hit.all())
        return state.x, state.v

    x0, v0 = x[:1, 4].clone().requires_grad_(True), v[:1, 4].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(one_step, (x0, v0), eps=1e-7, atol=1e-5, rtol=1e-4)


@pytest.mark.slow
def test_one_toi_step_of_a_rope_limit_passes_gradcheck():
    """Rope: the first step in which a limit becomes active (frame 10 -> 11 of seed 0, no contact before);
    with TOI the limit is met at its time of impact, and gradcheck in (x, v)."""
    task = build_task("Rope")
    with torch.no_grad():
        x, v, _ = simulator_for(task).rollout(task.sample(2, 0), task.params, task.dt, 12)
        gaps = task.system.detector.gaps(x[0])
    assert (gaps[10] > 0).all() and (gaps[11] < 0).sum() == 1
    # the end-of-step rule's penetration target is not differentiated (paper Suppl. F): without it for gradcheck
    sim = simulator_for(build_task("Rope", overrides={"contact": {"compensation": 0.0}}), time_of_impact=True)
    with torch.no_grad():
        after, hit = sim.step(State(x[:1, 10], v[:1, 10]), task.params, task.dt)
    # e = 0: after the impact the spring and gravity press the link on into its limit for the rest of the step,
    # which the end-of-step rule handles; the depth left is a small fraction of the published scheme's
    assert bool(hit[0]) and 0 > task.system.detector.gaps(after.x).min() > 0.05 * gaps[11].min()

    def one_step(xx, vv):
        state, _ = sim.step(State(xx, vv), task.params, task.dt)
        return state.x, state.v

    x0, v0 = x[:1, 10].clone().requires_grad_(True), v[:1, 10].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(one_step, (x0, v0), eps=1e-7, atol=1e-5, rtol=1e-4)


def _lstsq_target(constraints, xs, contacts, dt, compensation, A, lift):
    """The penetration target by a rank-revealing least squares alone (SVD, gelsd): the definition."""
    vd = torch.zeros(*contacts.active.shape, contacts.dc, dtype=xs.dtype)
    vd[..., 0] = -compensation * contacts.gap / dt
    vd = vd.reshape(len(xs), -1, 1)
    if lift == "effective-mass":
        return (A @ torch.linalg.lstsq(A, vd, driver="gelsd").solution)[..., 0]
    J = contacts.J
    y = torch.linalg.lstsq(J, vd, driver="gelsd").solution
    if constraints.count:
        JE = constraints.jac(xs)
        y = y - JE.mT @ torch.linalg.solve(JE @ JE.mT, JE @ y)
    return (J @ y)[..., 0]


@pytest.mark.parametrize("name,frames", [("Rope", 60), ("CP3", 60), ("Gyro", 100), ("BD5", 60), ("Cube", 250)])
def test_penetration_target_agrees_with_a_rank_revealing_least_squares(name, frames):
    # the target takes a Cholesky solve where the rows in use are far from rank-deficient, and the SVD elsewhere:
    # the same answer either way, on frames of the task's own rollouts (float64), the Cube's resting ones included
    # (A of rank 6 in 12 rows)
    from diffcontact.contact.effective_mass import effective_inverse_inertia
    from diffcontact.dynamics.inertia import inverse_factor_blocks

    task = build_task(name)
    sim = simulator_for(task)
    model = sim.contact_model
    with torch.no_grad():
        x, _, _ = sim.rollout(task.sample(8, 0), task.params, task.dt, frames)
        flat = x.flatten(0, 1)
        hit = (task.system.detector.gaps(flat) < 0).any(1)
        xs_all = flat[hit]
        contacts = task.system.detector.detect(xs_all)
        assert contacts is not None and len(contacts.index) >= 5
        xs = xs_all[contacts.index]
        _, A = effective_inverse_inertia(
            inverse_factor_blocks(task.params.inertia), task.system.constraints, xs, contacts.J
        )
        got = model.target_velocity(task.system.constraints, xs, contacts, task.dt, A)
        want = _lstsq_target(task.system.constraints, xs, contacts, task.dt, model.compensation, A, model.lift)
    scale = want.abs().max().clamp_min(1e-12)
    assert (got - want).abs().max() <= 1e-9 * scale
