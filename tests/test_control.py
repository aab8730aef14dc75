"""Control through contacts: the objectives' gradients against finite differences (float64), and each
control example lowering its loss by >= 90 % on a short run (reduced billiards table, the BD1 throws)."""

from __future__ import annotations

import json

import pytest
import torch

from diffcontact.control.billiards import Billiards
from diffcontact.control.optimise import InfeasibleControlError, adam, levenberg_marquardt, residual_and_jacobian
from diffcontact.control.throw import Physics, Throw

F64 = torch.float64


def small_table(goal=None) -> Billiards:
    """Three balls, the cue close to the triangle and fast: 60 frames (0.18 s) with two or three impacts."""
    return Billiards.build(balls=3, frames=60, cue_position=(0.4, 0.5), cue_velocity=(1.0, 0.0), goal=goal)


def reachable_table() -> Billiards:
    """The reduced table with its goal where the last ball ends for another shot than θ0."""
    probe = small_table()
    with torch.no_grad():
        x, _, _ = probe.rollout(torch.tensor([[0.4, 0.495, 1.15, 0.08]], dtype=F64))
    return small_table(goal=tuple(x[0, -1, -1].tolist()))


def loss_of(problem, theta: torch.Tensor) -> torch.Tensor:
    r = problem.residual(theta[None])[0]
    return (r * r).sum()


def central_difference(f, theta: torch.Tensor, index: int, h: float) -> float:
    e = torch.zeros_like(theta)
    e[index] = h
    return float((f(theta + e) - f(theta - e)) / (2 * h))


def test_billiards_loss_gradient_wrt_cue_velocity_matches_finite_differences():
    shot = small_table()
    theta = shot.theta0.clone().requires_grad_(True)
    loss = loss_of(shot, theta)
    (grad,) = torch.autograd.grad(loss, theta)
    with torch.no_grad():
        _, hit, _ = shot.rollout(shot.theta0[None])
        assert int(hit.sum()) >= 2  # the horizon holds impacts: the gradient goes through them
        fd = [central_difference(lambda t: loss_of(shot, t), shot.theta0, i, 1e-6) for i in (2, 3)]
    assert abs(float(grad[2])) > 1e-3 and abs(float(grad[3])) > 1e-3
    for i, expect in zip((2, 3), fd):
        assert abs(float(grad[i]) - expect) <= 1e-6 * max(1.0, abs(expect)), (i, float(grad[i]), expect)


@pytest.mark.slow
def test_throw_landing_gradient_through_the_impact_time_matches_finite_differences():
    throw = Throw(Physics.true(), "hit")
    theta0 = torch.tensor([0.5, 0.3, -2.0], dtype=F64)
    _, J = residual_and_jacobian(throw.residual, theta0[None])
    with torch.no_grad():
        for i in range(3):
            fd = central_difference(lambda t: throw.residual(t[None])[0, 0], theta0, i, 1e-6)
            assert abs(float(J[0, 0, i]) - fd) <= 1e-6 * max(1.0, abs(fd)), (i, float(J[0, 0, i]), fd)
    assert J[0, 1].abs().max() < 1e-9  # the landing height is the radius, whatever the throw


@pytest.mark.slow
def test_batched_throws_equal_single_throws():
    """Candidates in one batch bounce at different frames; each row equals its own simulation."""
    throw = Throw(Physics.true(), "hit")
    thetas = torch.tensor([[0.5, 0.3, -2.0], [0.2, -0.5, 4.0]], dtype=F64)
    with torch.no_grad():
        together = throw.residual(thetas)
        alone = torch.cat([throw.residual(t[None]) for t in thetas])
        _, _, found = throw.bounce_frames(thetas)
    assert found[0, 1] != found[1, 1]
    assert torch.allclose(together, alone, rtol=0, atol=1e-12)


def test_billiards_reduced_problem_loss_falls_by_90_percent():
    shot = reachable_table()
    hist = levenberg_marquardt(shot.residual, shot.theta0, 12, scale=torch.full((4,), 0.1, dtype=F64), radius=0.5)
    assert hist.loss <= 0.1 * hist.losses[0], hist.losses
    assert hist.losses[0] > 1e-5  # (the start is not already at the goal)


def test_billiards_search_lines_are_seeded_and_its_speeds_give_the_predicted_distances():
    """The search's shot (p, s·v) ends where (p, v) is at s·T (no walls, no forces): simulating each candidate at
    its chosen speed gives the distance the search predicted from the top-speed path."""
    shot = reachable_table()
    seeded = [shot.aim_lines(16, torch.Generator().manual_seed(seed), speed=1.5) for seed in (3, 3, 4)]
    lines = seeded[0]
    assert torch.equal(lines, seeded[1]) and not torch.equal(lines[1:], seeded[2][1:])
    assert torch.allclose(lines[:, 2:].norm(dim=1), torch.full((16,), 1.5, dtype=F64))
    assert torch.allclose(lines[0, 2:] / 1.5, shot.theta0[2:] / shot.theta0[2:].norm())  # (θ0's line first)
    found = shot.search(16, seed=3, rounds=2, elites=4)
    assert (found.distances[1:] >= found.distances[:-1]).all() and 16 <= len(found.thetas) <= 32
    assert torch.isfinite(found.distances).all()  # (dropped: shots that never move the last ball)
    assert len(found.nearest) == 2 and found.nearest[1] <= found.nearest[0] == float(found.distances[0])
    with torch.no_grad():
        r = shot.residual(found.thetas[:6])
    assert torch.allclose(r.norm(dim=1), found.distances[:6], rtol=0, atol=1e-9), (r.norm(dim=1), found.distances)
    with torch.no_grad():
        r0 = shot.residual(shot.theta0[None])
    assert float(found.distances[0]) < 0.1 * float(r0.norm())  # (the search beats the task file's shot)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["hit", "vertical"])
def test_throws_loss_falls_by_90_percent(mode):
    throw = Throw(Physics.true(), mode)
    scale = torch.tensor([1.0, 1.0, 10.0] if mode == "hit" else [10.0], dtype=F64)
    hist = levenberg_marquardt(throw.residual, throw.theta0, 8, tol=1e-12, scale=scale)
    assert hist.loss <= 0.1 * hist.losses[0] and hist.losses[0] > 1e-3, hist.losses
    landings = throw.landings(hist.theta)
    if mode == "hit":
        assert abs(landings[1][0] - 0.75) < 1e-4
    else:  # a vertical rebound: the second impact is where the first was
        assert abs(landings[1][0] - landings[0][0]) < 1e-4


def test_adam_lowers_the_vertical_throw_loss():
    throw = Throw(Physics.true(), "vertical")
    hist = adam(throw.residual, throw.theta0, 6, lr=0.4, scale=torch.tensor([10.0], dtype=F64))
    assert hist.loss <= 0.1 * hist.losses[0], hist.losses


def test_levenberg_marquardt_solves_a_linear_least_squares_problem_in_one_step():
    A = torch.tensor([[2.0, 1.0, 0.0], [0.0, 1.0, 3.0]], dtype=F64)
    b = torch.tensor([1.0, -2.0], dtype=F64)
    hist = levenberg_marquardt(lambda t: t @ A.T - b, torch.zeros(3, dtype=F64), 5, tol=1e-20, damping=1e-14)
    assert hist.simulations == 2 and hist.loss < 1e-20  # (the minimum-norm solution of A θ = b)
    assert torch.allclose(hist.theta, torch.linalg.pinv(A) @ b, atol=1e-10)


def test_levenberg_marquardt_moves_several_starts_at_once_and_keeps_the_best():
    """Two starts in one batch: one on a flat piece (zero gradient: it stays), one that solves A θ = b."""
    A = torch.tensor([[2.0, 1.0, 0.0], [0.0, 1.0, 3.0]], dtype=F64)
    b = torch.tensor([1.0, -2.0], dtype=F64)

    def residual(t):
        return torch.where(t[:, :1] > 0, t @ A.T - b, torch.full_like(t[:, :2], 5.0))

    starts = torch.tensor([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64)
    hist = levenberg_marquardt(residual, starts, 5, tol=1e-20, damping=1e-14)
    assert hist.simulations == 2 and hist.trajectories == 3 and hist.loss < 1e-20
    expect = starts[1] + torch.linalg.pinv(A) @ (b - A @ starts[1])  # (the minimum-norm step from start 2)
    assert torch.allclose(hist.theta, expect, atol=1e-10)
    flat = levenberg_marquardt(residual, starts[:1], 5)
    assert flat.stop == "the gradient is zero" and flat.simulations == 1 and flat.loss == 50.0


def test_infeasible_controls_have_infinite_residuals_and_are_errors_at_the_start():
    shot = small_table()
    on_a_ball = torch.tensor([[0.5, 0.5, 1.0, 0.0], [0.4, 0.5, 1.0, 0.0]], dtype=F64)
    with torch.no_grad():
        r = shot.residual(on_a_ball)
    assert torch.isinf(r[0]).all() and torch.isfinite(r[1]).all()
    with pytest.raises(InfeasibleControlError, match="infeasible"):
        levenberg_marquardt(shot.residual, on_a_ball[0], 3)
    throw = Throw(Physics.true(), "hit", max_frames=20)  # (0.2 s: the disk has not reached the ground)
    with torch.no_grad():
        assert torch.isinf(throw.residual(throw.theta0[None])).all()
    with pytest.raises(InfeasibleControlError, match="fewer than 2 bounces"):
        throw.landings(throw.theta0)


@pytest.mark.slow
def test_control_throw_command_writes_its_outputs(tmp_path):
    from typer.testing import CliRunner

    from diffcontact.cli import app

    args = ["control", "throw", "--mode", "vertical", "--out", str(tmp_path), "--no-gif", "--no-progress"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    result = json.loads((tmp_path / "throw.json").read_text())
    assert result["vertical"]["true"]["best_loss"] < 1e-10 and "torch" in result["versions"]
    assert (tmp_path / "throw_vertical_loss.png").stat().st_size > 0
    res = CliRunner().invoke(app, [*args, "--from", str(tmp_path / "no-run")])
    assert res.exit_code == 2 and "not a run directory" in res.output


def test_control_billiards_command_writes_its_outputs(tmp_path):
    """A 3-ball table over 40 frames: the cue does not reach the triangle, the gradient is zero and LM says so."""
    from typer.testing import CliRunner

    from diffcontact.cli import app

    args = ["control", "billiards", "--balls", "3", "--frames", "40", "--out", str(tmp_path), "--no-progress"]
    res = CliRunner().invoke(app, [*args, "--max-simulations", "3", "--no-gif", "--search-shots", "0"])
    assert res.exit_code == 0, res.output
    result = json.loads((tmp_path / "billiards.json").read_text())
    assert result["stop"] == "the gradient is zero" and result["simulations"] == 1
    assert result["config"]["balls"] == 3 and "final_state" not in result["published"] and result["search"] is None
    assert (tmp_path / "billiards_loss.png").stat().st_size > 0
    res = CliRunner().invoke(app, [*args, "--optimiser", "sgd"])
    assert res.exit_code == 2 and "optimiser = 'sgd' is not one of" in res.output


def test_control_billiards_command_searches_then_optimises(tmp_path):
    """The global stage counts as one simulation of all its shots, with its seed in the JSON."""
    from typer.testing import CliRunner

    from diffcontact.cli import app

    args = ["control", "billiards", "--balls", "3", "--frames", "60", "--out", str(tmp_path), "--no-progress"]
    more = ["--max-simulations", "4", "--no-gif", "--search-shots", "12", "--search-rounds", "2", "--seed", "5"]
    res = CliRunner().invoke(app, [*args, *more])
    assert res.exit_code == 0, res.output
    result = json.loads((tmp_path / "billiards.json").read_text())
    assert result["search"]["shots"] == 24 and result["config"]["seed"] == 5
    assert result["simulations"] == 2 + result["optimisation"]["simulations"] <= 4
    assert result["trajectories"] == 24 + result["optimisation"]["trajectories"]
    assert result["losses"][:2] == pytest.approx([d**2 for d in result["search"]["nearest_per_round_m"]])
    assert result["best_loss"] <= result["losses"][2] == pytest.approx(result["losses"][1], rel=1e-6, abs=1e-18)
