"""The standard errors of learned μ and e (train/identify.py): their information JᵀJ against an independent
finite-difference Hessian of the squared residuals, their scaling with the data, and a property nothing in the data
moves marked not identified."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from diffcontact.data.generate import make_split
from diffcontact.models.model import build_model
from diffcontact.state import State
from diffcontact.systems.registry import build_task
from diffcontact.train.identify import chunk_slots, evidence, information, refine

DATA = Path(__file__).parent / "data"


def _true_model(task):
    """A CM-CD-CLNN model of ``task`` holding its true masses, μ, e and potential."""
    net = build_model(task, "CM-CD-CLNN", potential="known")
    with torch.no_grad():
        net.params.log_mass.copy_(task.params.inertia.masses.log())
        net.params.mu_raw.copy_(task.params.mu[: net.params.mu_raw.numel()])
        net.params.e_raw.copy_(task.params.e[: net.params.e_raw.numel()])
    return net


def _chunks(task, n: int, seed: int, noise: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    split = make_split(task, n, seed=seed, frames=40, noise=noise, progress=False)
    return torch.from_numpy(split["chunk_x"]), torch.from_numpy(split["chunk_v"])


def test_the_information_is_the_finite_difference_hessian_of_the_squared_residuals():
    # noise-free chunks and the true model: the residuals vanish, so JᵀJ is the Hessian of S = ½‖r‖² exactly
    task = build_task("BP1")
    x, v = _chunks(task, 60, seed=3)
    net = _true_model(task)
    sim, base = net.simulator, net.params()
    base = base.replace(mu=base.mu.detach(), e=base.e.detach())
    slots = torch.ones(task.system.n_slots, dtype=torch.bool)
    hit = chunk_slots(sim, base, x, v, task.dt).any(1)  # (one μ and e shared by the four walls)
    xs, vs = x[hit], v[hit]
    assert 10 < len(xs) < len(x)
    JtJ = information(sim, base, xs, vs, task.dt, slots)

    def S(mu: float, e: float) -> float:  # (independently of train/identify.py: a rollout of every chunk)
        params = base.replace(mu=torch.full_like(base.mu, mu), e=torch.full_like(base.e, e))
        with torch.no_grad():
            px, pv, _ = sim.rollout(State(xs[:, 0], vs[:, 0]), params, task.dt, xs.shape[1])
        return 0.5 * float((px - xs).square().sum() + (pv - vs).square().sum())

    mu0, e0, h = 0.2, 0.8, 1e-4
    f = {(i, j): S(mu0 + i * h, e0 + j * h) for i in (-1, 0, 1) for j in (-1, 0, 1)}
    cross = (f[1, 1] - f[1, -1] - f[-1, 1] + f[-1, -1]) / 4
    H = (
        torch.tensor(
            [[f[1, 0] - 2 * f[0, 0] + f[-1, 0], cross], [cross, f[0, 1] - 2 * f[0, 0] + f[0, -1]]], dtype=torch.float64
        )
        / h**2
    )
    assert torch.allclose(JtJ, H, rtol=1e-4, atol=1e-6 * float(H.abs().max()))


def test_noisy_data_give_finite_standard_errors_and_the_marking_follows_them():
    task = build_task("BP1")
    x, v = _chunks(task, 60, seed=3, noise=0.01)
    ev = evidence(_true_model(task), x, v)
    assert ev["chunks"][0] > 10  # (chunks with a collision: the evidence)
    se = (ev["mu"]["std_error"][0], ev["e"]["std_error"][0])
    assert all(0 < s < 1 for s in se)
    assert ev["mu"]["identified"] == [se[0] <= 0.005] and ev["e"]["identified"] == [se[1] <= 0.005]
    # ten times the data: about √10 times smaller errors
    x, v = _chunks(task, 600, seed=3, noise=0.01)
    more = evidence(_true_model(task), x, v)
    ratio = [a / b for a, b in zip(se, (more["mu"]["std_error"][0], more["e"]["std_error"][0]))]
    assert all(2.0 < q < 5.0 for q in ratio), ratio


def test_a_property_nothing_moves_has_no_standard_error_and_is_not_identified():
    # the rope's limits are one-dimensional (no tangent): nothing in any data depends on μ.  e is taken at 0.03, not
    # at its true 0, where no restitution bound e·f_c is active on these chunks and the residuals do not move with e
    # to first order (its derivative there was rounding, 5.5e-12, while the penetration target carried an SVD's)
    task = build_task("Rope")
    x, v = _chunks(task, 12, seed=4)
    net = _true_model(task)
    with torch.no_grad():
        net.params.e_raw.fill_(0.03)
    ev = evidence(net, x, v)
    assert ev["chunks"][0] > 0
    assert ev["mu"] == {"std_error": [None], "bootstrap_error": [None], "identified": [False]}
    assert ev["e"]["std_error"][0] is not None and math.isfinite(ev["e"]["std_error"][0])


def test_refinement_moves_what_the_data_identify_to_the_truth_and_leaves_the_rest():
    # the rope, every property true but e (0.03 against 0: a local refinement, from near) and μ (0.5: nothing depends
    # on it, the limits have no tangent). Near e = 0 the residuals grow faster than e²: Gauss-Newton converges linearly
    task = build_task("Rope")
    x, v = _chunks(task, 12, seed=4)
    net = _true_model(task)
    with torch.no_grad():
        net.params.mu_raw.fill_(0.5)
        net.params.e_raw.fill_(0.03)
    record = refine(net, x, v)
    assert record["mu_before"] == [0.5] and record["e_before"] == [pytest.approx(0.03)] and record["iterations"] > 0
    assert float(net.params.mu_raw.detach()) == 0.5
    assert float(net.params.e_raw.detach()) == pytest.approx(float(task.params.e[0]), abs=2e-3)


def test_where_the_model_is_right_and_the_noise_small_the_bootstrap_agrees_with_the_standard_error():
    # an unbiased estimator: a refit on data simulated again with fresh noise spreads as the chunks do
    task = build_task("BP1")
    x, v = _chunks(task, 600, seed=3, noise=1e-4)
    ev = evidence(_true_model(task), x, v, noise=1e-4)
    for key in ("mu", "e"):
        se, boot = ev[key]["std_error"][0], ev[key]["bootstrap_error"][0]
        assert 1 / 3 < boot / se < 3, (key, se, boot)
        assert ev[key]["identified"] == [se <= 0.005 and boot <= 0.005] == [True]
    assert evidence(_true_model(task), x, v)["e"]["bootstrap_error"] == [None]  # (no noise recorded: no bootstrap)


def test_the_bootstrap_marks_a_restitution_biased_by_noisy_first_states_as_not_identified():
    # a Rope trained on data with noise 0.05 (a link's length): CM-CD-CLNN's learned model (its masses, potential
    # and e = 0.299; the truth is 0) and 16 of its training chunks.  Their standard error is 0.004, which alone would
    # mark e identified; every chunk starts from a noisy state, which biases e without widening its spread
    task = build_task("Rope")
    stored = torch.load(DATA / "rope_noisy_biased_model.pt", weights_only=True)
    net = build_model(task, "CM-CD-CLNN", potential="linked")
    net.load_state_dict(stored["state_dict"])
    ev = evidence(net, stored["chunk_x"], stored["chunk_v"], noise=stored["noise"])
    assert float(net.params.e_raw.detach()) == pytest.approx(0.2988, abs=1e-4)
    assert ev["e"]["std_error"][0] < 0.005 and ev["e"]["bootstrap_error"][0] > 0.05
    assert ev["e"]["identified"] == [False]
    assert ev["mu"] == {"std_error": [None], "bootstrap_error": [None], "identified": [False]}  # (nothing moves μ)
