"""The training step's shortcuts equal what they replace (float64): the learned and the known potentials'
closed-form forces against autograd's gradient (values and gradients), the point-mass scaling of apply_blocks
against the dense mass matrix, and a model's rollout with the shortcuts against one through autograd."""

from __future__ import annotations

import pytest
import torch

from diffcontact.dynamics.inertia import apply_blocks, body_blocks, dense
from diffcontact.dynamics.lagrangian import potential_force
from diffcontact.dynamics.potentials import gradient_force
from diffcontact.errors import ConfigError
from diffcontact.models import build_model
from diffcontact.models.params import LearnedGravity, LinkedPotential, MLPPotential
from diffcontact.state import ForcePotential, Inertia, Params
from diffcontact.systems import build_task

TOL = 1e-12  # float64: rounding only


def _autograd_force(potential, x, inertia=None):
    """−∇V by autograd with the graph kept (the path the closed form replaces); a network's V ignores the inertia."""
    with torch.enable_grad():
        xg = x if x.requires_grad else x.detach().requires_grad_(True)
        (g,) = torch.autograd.grad(potential(xg).sum(), xg, create_graph=True)
    return -g


@pytest.mark.parametrize("task_name", ["BP5", "CP3", "Rope", "Gyro", "Cube"])
def test_known_potentials_force_equals_autograd_gradient_and_its_derivatives(task_name):
    """Gravity (on each body's centre of mass: the box's off its centre), the rope's springs (to its anchor too) and
    their sum: the written-out force against autograd's gradient of V, and the force's derivatives w.r.t. the
    positions, the masses and the box's centre of mass."""
    task = build_task(task_name)
    gen = torch.Generator().manual_seed(3)
    pot = task.params.potential
    assert isinstance(pot, ForcePotential)
    x = task.sample(3, seed=3).x
    x = (x + 0.01 * torch.randn(x.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)
    true = task.params.inertia
    masses = true.masses * (1 + 0.1 * torch.rand(true.masses.shape, generator=gen))
    masses = masses.to(torch.float64).requires_grad_(True)
    com = None if true.com is None else (0.01 * torch.randn(true.com.shape, generator=gen, dtype=torch.float64))
    inertia = Inertia(masses, true.moments, None if com is None else com.requires_grad_(True))
    w = torch.randn(x.shape, generator=gen, dtype=torch.float64)
    fast, slow = pot.force(x, inertia), gradient_force(pot, x, inertia)
    assert torch.allclose(fast, slow, rtol=0, atol=TOL)
    assert (fast.abs().max() > 0) == bool(pot.terms)  # (BP5: no gravity, an empty sum)
    assert torch.equal(potential_force(task.params, x), pot.force(x, task.params.inertia))  # (dynamics use it)
    if not pot.terms:
        return
    wrt = [x, masses] + ([] if com is None else [inertia.com])
    ga = torch.autograd.grad((fast * w).sum(), wrt, allow_unused=True, materialize_grads=True)
    gb = torch.autograd.grad((slow * w).sum(), wrt, allow_unused=True, materialize_grads=True)
    for a, b in zip(ga, gb):
        assert torch.allclose(a, b, rtol=0, atol=1e-10)
    if com is not None:  # (the force's moment about the box's centre is that of m g at the centre of mass)
        assert ga[-1].abs().max() > 0


def test_learned_gravity_force_equals_autograd_gradient():
    pot = LearnedGravity(4, generator=torch.Generator().manual_seed(0))
    x = torch.randn(2, 8, 3, dtype=torch.float64)
    inertia = Inertia(torch.tensor([0.5, 2.0], dtype=torch.float64), torch.ones(2, 3, dtype=torch.float64))
    fast, slow = pot.force(x, inertia), gradient_force(pot, x, inertia)
    assert torch.allclose(fast, slow, rtol=0, atol=TOL) and fast[:, 1::4].abs().max() == 0
    (a,) = torch.autograd.grad(fast.sum(), pot.log_g)
    (b,) = torch.autograd.grad(slow.sum(), pot.log_g)
    assert torch.allclose(a, b, rtol=0, atol=TOL)


@pytest.mark.parametrize("layers", [1, 3])
def test_mlp_force_equals_autograd_gradient_and_its_derivatives(layers):
    gen = torch.Generator().manual_seed(layers)
    pot = MLPPotential(6, 16, layers, generator=gen).double()
    assert isinstance(pot, ForcePotential)
    x = torch.randn(4, 3, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    w = torch.randn(4, 3, 2, generator=gen, dtype=torch.float64)
    fast, slow = pot.force(x), _autograd_force(pot, x)
    assert torch.allclose(fast, slow, rtol=0, atol=TOL)
    unit = Params(Inertia(torch.ones(3, dtype=torch.float64), torch.zeros(3, 0, dtype=torch.float64)), pot, None, None)
    assert torch.equal(potential_force(unit, x), fast)  # (the dynamics use the closed form)
    params = [p for p in pot.parameters() if p is not pot.net[-1].bias]  # (the force does not depend on it)
    ga = torch.autograd.grad((fast * w).sum(), [x, *params])
    gb = torch.autograd.grad((slow * w).sum(), [x, *params])
    for a, b in zip(ga, gb):
        assert torch.allclose(a, b, rtol=0, atol=TOL)
    assert torch.autograd.gradcheck(lambda y: pot.force(y), (x,))


def test_mlp_force_without_hidden_layers_is_constant():
    pot = MLPPotential(6, 16, 0, generator=torch.Generator().manual_seed(0)).double()
    x = torch.randn(4, 3, 2, dtype=torch.float64)
    assert torch.allclose(pot.force(x), _autograd_force(pot, x), rtol=0, atol=TOL)


def test_linked_force_equals_autograd_gradient_and_its_derivatives():
    """The rope's learned potential (the network plus one of each link's stretch, the first link to the anchor):
    its written-out force against autograd's, and the force's gradients with respect to x and the weights."""
    task = build_task("Rope")
    gen = torch.Generator().manual_seed(2)
    pot = LinkedPotential(20, task.system.links, 16, 2, generator=gen).double()
    x = task.sample(4, seed=2).x  # (links at their rest length: stretch 0)
    x = (x + 0.003 * torch.randn(x.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)
    w = torch.randn(4, 10, 2, generator=gen, dtype=torch.float64)
    fast, slow = pot.force(x), _autograd_force(pot, x)
    assert torch.allclose(fast, slow, rtol=0, atol=TOL)
    assert fast[:, 0].abs().max() > 0 and (fast - pot.body.force(x)).abs().max() > 1.0  # (the links' term acts)
    params = [p for p in pot.parameters() if p is not pot.body.net[-1].bias and p is not pot.pair.net[-1].bias]
    ga = torch.autograd.grad((fast * w).sum(), [x, *params])
    gb = torch.autograd.grad((slow * w).sum(), [x, *params])
    for a, b in zip(ga, gb):
        assert torch.allclose(a, b, rtol=0, atol=1e-10)


def test_linked_potential_needs_a_system_with_links():
    with pytest.raises(ConfigError, match="linked.*links"):
        build_model(build_task("BP5-e"), "CM-CD-CLNN", potential="linked", hidden=8)
    net = build_model(build_task("Rope"), "CM-CD-CLNN", potential="linked", hidden=8)
    assert isinstance(net.params.potential, LinkedPotential)


def test_apply_blocks_point_masses_equal_the_dense_mass_matrix():
    gen = torch.Generator().manual_seed(0)
    inertia = Inertia(masses=torch.rand(5, generator=gen, dtype=torch.float64) + 0.5, moments=torch.zeros(5, 0))
    M, Minv = body_blocks(inertia)
    y = torch.randn(3, 5, 2, 4, generator=gen, dtype=torch.float64)  # (B, P, d, k)
    for blocks in (M, Minv):
        want = (dense(blocks, 2) @ y.reshape(3, 10, 4)).reshape(y.shape)
        assert torch.allclose(apply_blocks(blocks, y), want, rtol=0, atol=TOL)


@pytest.mark.parametrize("name", ["CP3", "BD5"])
def test_model_rollout_and_gradients_equal_the_autograd_path(name, monkeypatch):
    """A learned model's rollout and parameter gradients, with the closed-form force, equal those with autograd's."""
    task = build_task(name)
    net = build_model(task, "CM-CD-CLNN", hidden=32, seed=1)  # float64
    state = task.sample(6, 3)

    def run():
        net.zero_grad()
        xs, vs = net(state.x, state.v, 4)
        (xs.square().sum() + vs.square().sum()).backward()
        return xs.detach(), [p.grad.clone() for p in net.parameters() if p.grad is not None]

    fast_x, fast_g = run()
    monkeypatch.setattr(MLPPotential, "force", _autograd_force)
    slow_x, slow_g = run()
    assert torch.allclose(fast_x, slow_x, rtol=0, atol=TOL)
    assert len(fast_g) == len(slow_g) > 0
    for a, b in zip(fast_g, slow_g):
        assert torch.allclose(a, b, rtol=1e-9, atol=TOL * max(1.0, float(b.abs().max())))
