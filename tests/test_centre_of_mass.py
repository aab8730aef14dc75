"""A box whose centre of mass is off its centre: the mass blocks against the rigid body's kinetic energy in closed
form, gravity's torque, free flight (the centre of mass on its parabola, angular momentum about it conserved), the
same tosses as a model whose points are the centre of mass, rest, and the learned offset's gradient (float64)."""

from __future__ import annotations

import pytest
import torch

from diffcontact import build_task
from diffcontact.dynamics.inertia import body_blocks, inverse_factor_blocks, kinetic_energy
from diffcontact.errors import ConfigError
from diffcontact.models import build_model
from diffcontact.simulator import simulator_for
from diffcontact.state import Inertia, State
from diffcontact.systems import box
from diffcontact.systems.poses import hat, points_to_pose, pose_to_points, quaternion_to_matrix
from diffcontact.train.summary import baseline_summary

F64 = torch.float64
HALF = 0.0524
COM = (0.004, -0.003, 0.009)  # m, body frame


def _random_inertia(n: int, gen: torch.Generator) -> Inertia:
    return Inertia(
        torch.rand(n, generator=gen, dtype=F64) + 0.2,
        0.5e-3 + 1e-3 * torch.rand(n, 3, generator=gen, dtype=F64),
        0.02 * torch.randn(n, 3, generator=gen, dtype=F64),
    )


def _state(position, quaternion, velocity=(0, 0, 0), omega=(0, 0, 0)) -> State:
    t = lambda a: torch.tensor([a], dtype=F64)  # noqa: E731
    return State(*pose_to_points(t(position), t(quaternion), t(velocity), t(omega)))


def _cube(com=COM, **contact):
    return build_task("Cube", {"body": {"centre_of_mass": list(com)}, **({"contact": contact} if contact else {})})


def test_mass_blocks_give_the_rigid_body_kinetic_energy_and_invert_in_closed_form():
    """½ vᵀ M v = ½ m |v_G|² + ½ ωᵀ I_G ω, I_G = m diag(Σμ − μ_k) (body frame), v_G the centre of mass's velocity;
    M M⁻¹ = I and L Lᵀ = M⁻¹; a centre of mass of 0 gives the blocks of a body without one."""
    gen = torch.Generator().manual_seed(0)
    inertia = _random_inertia(5, gen)
    q = torch.randn(5, 4, generator=gen, dtype=F64)
    q = q / q.norm(dim=-1, keepdim=True)
    v, w = torch.randn(5, 3, generator=gen, dtype=F64), torch.randn(5, 3, generator=gen, dtype=F64)
    x, xv = pose_to_points(torch.zeros(5, 3, dtype=F64), q, v, w)
    R = quaternion_to_matrix(q)
    v_com = v + (R @ torch.linalg.cross(w, inertia.com)[..., None])[..., 0]
    mom = inertia.moments
    I_com = inertia.masses[:, None] * (mom.sum(-1, keepdim=True) - mom)  # (5, 3) principal moments
    closed = 0.5 * inertia.masses * (v_com**2).sum(-1) + 0.5 * (I_com * w**2).sum(-1)
    # (one body per batch element: each takes its own inertia)
    ours = torch.stack([kinetic_energy(Inertia(*(t[i : i + 1] for t in inertia.__dict__.values())), xv[i : i + 1])[0]
                        for i in range(5)])  # fmt: skip
    assert torch.allclose(ours, closed, rtol=1e-12, atol=0)
    M, Minv = body_blocks(inertia)
    eye = torch.eye(4, dtype=F64).expand(5, 4, 4)
    assert (M @ Minv - eye).abs().max() <= 1e-10
    L = inverse_factor_blocks(inertia)
    assert (L @ L.mT - Minv).abs().max() <= 1e-10 * Minv.abs().max()
    zero = Inertia(inertia.masses, inertia.moments, torch.zeros_like(inertia.com))
    plain = Inertia(inertia.masses, inertia.moments)
    for a, b in zip(
        (*body_blocks(zero), inverse_factor_blocks(zero)), (*body_blocks(plain), inverse_factor_blocks(plain))
    ):
        assert torch.allclose(a, b, rtol=1e-15, atol=0)


def test_gravity_acts_at_the_centre_of_mass():
    """V = m g z_G (z_G the centre of mass's height), and its force's moment about the box's centre is that of
    −m g ẑ applied at the centre of mass."""
    task = _cube()
    s = _state((0.1, 0.2, 0.3), (0.9, 0.1, 0.3, 0.2))
    p, q, _, _ = points_to_pose(s.x, s.v)
    arm = (quaternion_to_matrix(q) @ torch.tensor(COM, dtype=F64)[:, None])[..., 0]  # (1, 3) world frame
    m = float(task.params.inertia.masses[0])
    assert float(task.params.potential_energy(s.x)[0]) == pytest.approx(
        m * 9.81 * float(p[0, 2] + arm[0, 2]), rel=1e-13
    )
    f = task.params.potential.force(s.x, task.params.inertia)[0]  # (4, 3)
    assert torch.allclose(f.sum(0), torch.tensor([0.0, 0.0, -m * 9.81], dtype=F64), rtol=0, atol=1e-13)
    torque = torch.linalg.cross(s.x[0] - p[0], f).sum(0)
    expected = torch.linalg.cross(arm[0], torch.tensor([0.0, 0.0, -m * 9.81], dtype=F64))
    assert torch.allclose(torque, expected, rtol=0, atol=1e-13)


def test_free_flight_keeps_the_centre_of_mass_on_its_parabola_and_its_angular_momentum():
    """A spinning box high above the table: its centre of mass follows p0 + v0 t − ½ g t² ẑ, its angular momentum
    about it (R I_G ω) and its energy stay constant. Both fail with gravity at the box's centre (a torque) or a mass
    matrix without the offset."""
    task = _cube()
    sim = simulator_for(task, "lagrangian", 0.0, None)
    s = _state((0.0, 0.0, 2.0), (0.9, 0.1, 0.3, 0.2), (0.5, -0.2, 0.1), (3.0, -2.0, 5.0))
    frames = 40
    xs, vs, _ = sim.rollout(s, task.params, task.dt, frames)
    p, q, v, w = points_to_pose(xs[0], vs[0])
    R = quaternion_to_matrix(q)
    com = torch.tensor(COM, dtype=F64)
    G = p + (R @ com[:, None])[..., 0]
    G_dot = v + (R @ torch.linalg.cross(w, com.expand_as(w))[..., None])[..., 0]
    t = torch.arange(frames, dtype=F64)[:, None] * task.dt
    parabola = G[0] + G_dot[0] * t - 0.5 * 9.81 * t**2 * torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    assert (G - parabola).abs().max() <= 1e-8
    inertia = task.params.inertia
    I_com = inertia.masses[0] * (inertia.moments[0].sum() - inertia.moments[0])
    L = (R @ (I_com * w)[..., None])[..., 0]
    assert (L - L[0]).abs().max() <= 1e-8 * L[0].norm()
    energy = task.system.energy(task.params, xs[0], vs[0])
    assert (energy - energy[0]).abs().max() <= 1e-7 * energy[0].abs()
    assert L[0].norm() > 1e-3 and (G[:, 2] - p[:, 2]).abs().max() > 1e-3  # (it spins; the offset matters)


def test_tosses_equal_those_of_a_model_whose_points_are_the_centre_of_mass(monkeypatch):
    """The same physics written two ways: this box, and a box with its centre of mass at 0 whose corners sit at
    −offset from it (its points are the centre of mass's), started from the same pose moved to the centre of mass.
    Tosses with impacts, friction and restitution agree to rounding."""
    ours = _cube()
    com = torch.tensor(COM, dtype=F64)
    corners = box.corners
    monkeypatch.setattr(box, "corners", lambda half: corners(half) - com)
    shifted = _cube(com=(0.0, 0.0, 0.0))
    monkeypatch.setattr(box, "corners", corners)
    start = ours.sample(4, seed=5)
    p, q, v, w = points_to_pose(start.x, start.v)
    R = quaternion_to_matrix(q)
    moved = State(*pose_to_points(p + (R @ com[:, None])[..., 0], q, v + (R @ hat(w) @ com[:, None])[..., 0], w))
    frames = 90
    xa, va, ca = simulator_for(ours, "lagrangian", 0.0, None).rollout(start, ours.params, ours.dt, frames)
    xb, vb, cb = simulator_for(shifted, "lagrangian", 0.0, None).rollout(moved, shifted.params, shifted.dt, frames)
    assert bool(ca.any()) and torch.equal(ca, cb)  # (they hit the table, on the same frames)
    pa, qa, _, _ = points_to_pose(xa, va)
    pb, qb, _, _ = points_to_pose(xb, vb)
    back = pb - (quaternion_to_matrix(qb) @ com[:, None])[..., 0]
    assert (pa - back).abs().max() <= 1e-9  # (1.2e-10 m measured)
    assert torch.minimum((qa - qb).abs().amax(-1), (qa + qb).abs().amax(-1)).max() <= 1e-12


@pytest.mark.parametrize("com", [(0.0, 0.0, 0.015), (0.015, -0.01, 0.0)])
def test_a_box_with_its_mass_off_centre_rests_on_a_face(com):
    task = _cube(com=com)
    sim = simulator_for(task, "lagrangian", 0.0, None)
    xs, vs, _ = sim.rollout(_state((0.0, 0.0, HALF), (1.0, 0.0, 0.0, 0.0)), task.params, task.dt, 150)
    p, q, v, w = points_to_pose(xs[0], vs[0])
    assert (HALF - p[:, 2]).max() <= 0.6e-3 and p[:, :2].abs().max() <= 1e-6
    assert (2 * torch.arccos(q[:, 0].abs().clamp(max=1.0))).max() <= 1e-5
    assert w.norm(dim=-1).max() <= 1e-4


def test_the_learned_centre_of_mass_starts_at_the_centre_and_its_gradient_matches_finite_differences():
    task = _cube(com=(0.0, 0.0, 0.0))
    net = build_model(task, "CM-CD-CLNN", potential="known", moments_init=1e-3)
    params = net.params
    assert params.com_raw is not None and torch.equal(params.inertia.com, torch.zeros(1, 3, dtype=F64))
    start = task.sample(2, seed=1)

    def loss(raw: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            params.com_raw.copy_(raw)
        x, _ = net(start.x, start.v, 25)
        return x[..., 0, 2].sum()  # the centres' heights over the frames

    raw = torch.tensor([[0.1, -0.2, 0.3]], dtype=F64)
    params.zero_grad()
    loss(raw).backward()
    grad = params.com_raw.grad.clone()
    h = 1e-6
    fd = torch.zeros_like(raw)
    for k in range(3):
        step = torch.zeros_like(raw)
        step[0, k] = h
        with torch.no_grad():
            fd[0, k] = (loss(raw + step) - loss(raw - step)) / (2 * h)
    assert grad.abs().max() > 1e-6
    assert torch.allclose(grad, fd, rtol=1e-5, atol=1e-9)


def test_a_centre_of_mass_outside_the_box_is_refused():
    with pytest.raises(ConfigError, match=r"body\.centre_of_mass = \[0\.0, 0\.0, 0\.06\] m lies outside the box"):
        _cube(com=(0.0, 0.0, 0.06))


def test_weights_without_a_centre_of_mass_load_as_a_uniform_box():
    net = build_model(_cube(), "CM-CD-CLNN", potential="known", moments_init=1e-3)
    saved = {k: v for k, v in net.state_dict().items() if not k.endswith("com_raw")}
    with torch.no_grad():
        net.params.com_raw.fill_(1.0)
    net.load_state_dict(saved)
    assert torch.equal(net.params.inertia.com, torch.zeros(1, 3, dtype=F64))


@pytest.mark.parametrize("name", ["MLP-CD-CLNN", "IN-CP-CLNN"])
def test_the_clnn_baselines_learn_the_box_inertia_as_the_contact_models_do(name):
    net = build_model(_cube(com=(0.0, 0.0, 0.0)), name, moments_init=1e-3)
    params = net.params
    moments = params.inertia.moments
    assert bool(((moments > 1e-3 * 0.5) & (moments < 1e-3 * 2.0)).all())  # (around moments_init, as CM-CD-CLNN's)
    assert params.com_raw is not None and torch.equal(params.inertia.com, torch.zeros(1, 3, dtype=F64))
    x0 = torch.tensor([[[0.0, 0.0, 0.3], [1.0, 0.0, 0.3], [0.0, 1.0, 0.3], [0.0, 0.0, 1.3]]], dtype=F64)
    v0 = torch.tensor([[[0.5, 0.0, 0.0]] * 4], dtype=F64) + torch.cross(
        torch.tensor([[0.0, 3.0, 1.0]], dtype=F64).expand(4, 3), x0[0] - x0[0, :1], dim=-1
    )
    x, _ = net(x0, v0, 5)
    x[..., 0, :].sum().backward()  # (free flight: the centre's path depends on where the mass is)
    assert params.com_raw.grad.abs().max() > 1e-8
    with torch.no_grad():
        params.com_raw.copy_(torch.tensor([[0.0, 0.1, 0.2]]))
    reported = baseline_summary(net, net_task := _cube(com=(0.0, 0.0, 0.0)), x.detach())["centre_of_mass"]
    assert reported["learned"] == pytest.approx((params.com_scale * torch.tensor([0.0, 0.1, 0.2])).tolist())
    assert reported["true"] == net_task.params.inertia.com.flatten().tolist()
