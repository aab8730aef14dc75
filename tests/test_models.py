"""Learnable models: the four variants build and run, gradients reach μ, e and masses, μ and e are learned."""

from __future__ import annotations

import pytest
import torch

import diffcontact as dc
from diffcontact.errors import ConfigError
from diffcontact.models import MODEL_NAMES, build_model

TOL_RECOVERED = 0.05  # a tiny run on a one-ball task recovers e and μ to within 0.05


def _colliding_chunks(task, n_traj: int, seed: int, frames: int = 5):
    """One 5-frame window per trajectory that starts out of contact and contains an impact."""
    sim = dc.simulator_for(task)
    with torch.no_grad():
        xs, vs, hit = sim.rollout(task.sample(n_traj, seed), task.params, task.dt, 100)
    X, V = [], []
    for b in range(n_traj):
        for s in range(100 - frames):
            if not hit[b, s] and hit[b, s + 1 : s + frames].any():
                X.append(xs[b, s : s + frames])
                V.append(vs[b, s : s + frames])
                break
    return torch.stack(X), torch.stack(V)


@pytest.mark.parametrize("name", list(MODEL_NAMES))
def test_every_model_runs_and_starts_from_frame_zero(name):
    task = dc.build_task("BD5")
    model = build_model(task, name, hidden=16, layers=1)
    state = task.sample(4, 0)
    xs, vs = model(state.x, state.v, 3)
    assert xs.shape == (4, 3, task.system.n_points, 2) and torch.isfinite(vs).all()
    assert torch.equal(xs[:, 0], state.x)


def test_unknown_model_and_transform_are_clear_errors():
    task = dc.build_task("BP1")
    with pytest.raises(ConfigError, match="model = 'CM-XX' is not one of"):
        build_model(task, "CM-XX")
    with pytest.raises(ConfigError, match="mu_transform = 'abs' is not one of"):
        build_model(task, mu_transform="abs")


def test_regularisation_of_cmr_models_can_be_set_and_only_there():
    task = dc.build_task("BP1")
    assert build_model(task, "CMr-CD-CLNN").simulator.contact_model.reg == 0.01
    assert build_model(task, "CMr-CD-CHNN", reg=1e-4).simulator.contact_model.reg == 1e-4
    with pytest.raises(ConfigError, match="reg = 0.001 is for the regularised models"):
        build_model(task, "CM-CD-CLNN", reg=1e-3)
    with pytest.raises(ConfigError, match="reg = 0 is not > 0"):
        build_model(task, "CMr-CD-CLNN", reg=0.0)


def test_homogeneous_tasks_learn_one_pair_and_others_one_per_slot():
    assert build_model(dc.build_task("BP5-e")).params.mu_raw.numel() == 1
    p = build_model(dc.build_task("BP5")).params
    assert p.mu_raw.numel() == 30 and p.e_raw.numel() == 30


@pytest.mark.parametrize("name", ["CM-CD-CLNN", "CMr-CD-CHNN"])
def test_loss_gradients_reach_mu_e_and_masses(name):
    task = dc.build_task("BD5")
    X, V = _colliding_chunks(task, 24, seed=1)
    model = build_model(task, name, hidden=16, layers=1, mu_transform="softplus", e_transform="sigmoid")
    px, pv = model(X[:, 0], V[:, 0], X.shape[1])
    loss = (px - X).abs().mean() + (pv - V).abs().mean()
    loss.backward()
    p = model.params
    for g in (p.mu_raw.grad, p.e_raw.grad, p.log_mass.grad, p.log_moments.grad):
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0


@pytest.mark.slow
def test_tiny_run_recovers_restitution_and_friction_of_one_ball():
    """BP1: one ball under gravity in a box, μ = 0.2, e = 0.8; 64 colliding chunks, 300 AdamW steps."""
    task = dc.build_task("BP1")
    X, V = _colliding_chunks(task, 64, seed=0)
    model = build_model(task, hidden=32, layers=2, mu_transform="softplus", e_transform="sigmoid", seed=0)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=1e-4)
    for _ in range(300):
        px, pv = model(X[:, 0], V[:, 0], X.shape[1])
        loss = (px - X).abs().mean() + (pv - V).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert abs(model.params.e[0].item() - 0.8) < TOL_RECOVERED
    assert abs(model.params.mu[0].item() - 0.2) < TOL_RECOVERED


def test_projected_coefficients_come_back_from_their_bounds():
    """A coefficient on its bound (e = 0, true 0.1) returns with the projected parametrisation; hardsigmoid's
    gradient there is zero and it stays (BD5: a slot with 34 collisions ended at e = 0, true 0.1)."""
    from diffcontact.models.params import LearnedParams

    def fit(e_transform, raw):
        p = LearnedParams(1, 0, 1, 2, 1, homogeneous=True, e_transform=e_transform, hidden=4, layers=1)
        with torch.no_grad():
            p.e_raw.fill_(raw)
        opt = torch.optim.Adam(p.parameters(), lr=1e-2)
        for _ in range(50):
            loss = ((p.e - 0.1) ** 2).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            p.project_()
        return p.e.item()

    assert abs(fit("projected", 0.0) - 0.1) < 0.02
    assert fit("hardsigmoid", -3.5) == 0.0
    p = LearnedParams(1, 0, 1, 2, 1, homogeneous=True)
    with torch.no_grad():
        p.mu_raw.fill_(-0.3)
        p.e_raw.fill_(1.4)
    p.project_()
    assert p.mu.item() == 0.0 and p.e.item() == 1.0
