"""The published trajectory metrics against values computed by hand on tiny arrays."""

from __future__ import annotations

import math

import pytest
import torch

import diffcontact as dc
from diffcontact.eval.metrics import (
    energy_deviation,
    error_curve,
    mean_interval,
    relative_error,
    trajectory_error,
    true_energy,
)


def _traj(values):  # (N, T, P=1, d) from nested lists (N, T, d)
    return torch.tensor(values, dtype=torch.float64)[:, :, None, :]


def test_relative_error_by_hand():
    # one trajectory, 2 frames, 1 point in 2-D: z_1 = (x, v) = (3, 0, 0, 4), ‖z_1‖ = 5
    x = _traj([[[1.0, 0.0], [3.0, 0.0]]])
    v = _traj([[[0.0, 1.0], [0.0, 4.0]]])
    x_hat = _traj([[[1.0, 0.0], [3.0, 3.0]]])  # off by 3 in one position entry
    v_hat = _traj([[[0.0, 1.0], [0.0, 0.0]]])  # off by 4 in one velocity entry
    rel = relative_error(x_hat, v_hat, x, v)
    assert rel.shape == (1, 2)
    assert rel[0, 0] == 0.0  # the initial state is given
    assert rel[0, 1].item() == pytest.approx(math.sqrt(9 + 16) / 5)


def test_relative_error_refuses_nan_zero_truth_and_shape_mismatch():
    x = _traj([[[1.0, 0.0], [2.0, 0.0]]])
    v = torch.zeros_like(x)
    bad = x.clone()
    bad[0, 1, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="trajectory 0, frame 1"):
        relative_error(bad, v, x, v)
    with pytest.raises(ValueError, match="frame 0 is zero"):
        relative_error(x, v, torch.zeros_like(x), v)
    with pytest.raises(ValueError, match="shapes differ"):
        relative_error(x[:, :1], v, x, v)


def test_trajectory_error_sums_the_first_five_frames():
    rel = torch.tensor([[0.0, 0.1, 0.2, 0.3, 0.4, 0.5], [0.0, 1.0, 1.0, 1.0, 1.0, 9.0]], dtype=torch.float64)
    assert trajectory_error(rel).tolist() == pytest.approx([1.0, 4.0])
    assert trajectory_error(rel, steps=2).tolist() == pytest.approx([0.1, 1.0])
    with pytest.raises(ValueError, match="steps = 7 is not in"):
        trajectory_error(rel, steps=7)


def test_mean_interval_student_t():
    mean, half = mean_interval(torch.tensor([1.0, 2.0, 3.0]))
    # std 1, sem 1/√3, t_{0.975, 2} = 4.302652729911275 (tables)
    assert mean == pytest.approx(2.0) and half == pytest.approx(4.302652729911275 / math.sqrt(3))
    assert mean_interval(torch.tensor([5.0])) == (5.0, None)
    with pytest.raises(ValueError, match="no values"):
        mean_interval(torch.tensor([]))


def test_error_curve_averages_over_trajectories():
    rel = torch.tensor([[0.0, 1.0, 3.0], [0.0, 3.0, 5.0]], dtype=torch.float64)
    assert error_curve(rel, frames=2).tolist() == [0.0, 2.0]
    assert error_curve(rel, frames=3).tolist() == [0.0, 2.0, 4.0]
    with pytest.raises(ValueError, match="frames = 4 is not in"):
        error_curve(rel, frames=4)


def test_true_energy_of_a_falling_point_mass_and_its_deviation():
    task = dc.build_task("BP1")  # one point mass m = 0.1 kg, g = 9.81 m/s² along −y
    x = _traj([[[0.5, 0.2], [0.5, 0.3]]])
    v = _traj([[[1.0, 2.0], [0.0, 0.0]]])
    energy, kinetic = true_energy(task, x, v)
    assert energy.shape == kinetic.shape == (1, 2)
    # ½ m |v|² + m g y, and ½ m |v|²
    assert energy[0].tolist() == pytest.approx([0.5 * 0.1 * 5 + 0.1 * 9.81 * 0.2, 0.1 * 9.81 * 0.3])
    assert kinetic[0].tolist() == pytest.approx([0.5 * 0.1 * 5, 0.0])
    dev = energy_deviation(energy + torch.tensor([[0.0, 0.01]], dtype=torch.float64), energy, kinetic)
    assert dev[0].tolist() == pytest.approx([0.0, 0.01 / 0.25])  # relative to the largest kinetic energy, 0.25 J
    # independent of the potential's zero: the same deviation with every energy shifted by 1 J
    assert energy_deviation(energy + 1.01, energy + 1, kinetic)[0].tolist() == pytest.approx([0.04, 0.04])
    with pytest.raises(ValueError, match="true trajectory 0 never moves"):
        energy_deviation(energy, energy, torch.zeros_like(energy))


def test_a_diverged_prediction_has_infinite_error_where_allowed():
    x = _traj([[[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]]])
    v = torch.zeros_like(x)
    bad = x.clone()
    bad[0, 2] = float("nan")
    rel = relative_error(bad, v, x, v, diverged_ok=True)
    assert rel[0, :2].tolist() == [0.0, 0.0] and rel[0, 2] == float("inf")


def test_predict_keeps_the_finite_prefix_of_a_diverging_trajectory():
    from diffcontact.eval.rollouts import predict

    class Diverging(torch.nn.Module):  # element with x0 > 0 "diverges" at frame 3: a rollout of > 3 frames raises
        def forward(self, x0, v0, frames):
            if frames > 3 and bool((x0 > 0).any()):
                raise FloatingPointError("frame 3: non-finite state")
            xs = x0[:, None] + torch.arange(frames, dtype=x0.dtype)[None, :, None, None]
            return xs, torch.zeros_like(xs)

    x0 = torch.tensor([[[-1.0, -1.0]], [[1.0, 1.0]], [[-2.0, -2.0]]], dtype=torch.float64)  # (3, 1, 2)
    xs, vs = predict(Diverging(), x0, torch.zeros_like(x0), 6, batch=2)
    assert xs.shape == (3, 6, 1, 2)
    assert torch.isfinite(xs[0]).all() and torch.isfinite(xs[2]).all()  # (the others are kept whole)
    assert torch.isfinite(xs[1, :3]).all() and torch.isnan(xs[1, 3:]).all()
    assert xs[1, :3, 0, 0].tolist() == [1.0, 2.0, 3.0]
