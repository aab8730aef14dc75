"""The tossed box: pose conversions, corner gaps and Jacobians, rest, free flight and a closed-form bounce."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffcontact import build_task
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems.poses import matrix_to_quaternion, points_to_pose, pose_to_points, quaternion_to_matrix

ROUND_TRIP = 1e-12
HALF = 0.0524


def _random_poses(n: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    return (torch.randn(n, 3, generator=gen, dtype=torch.float64) for _ in range(3)), q


def test_pose_and_points_round_trip():
    (p, v, w), q = _random_poses(500, 0)
    x, xv = pose_to_points(p, q, v, w)
    p2, q2, v2, w2 = points_to_pose(x, xv)
    for a, b in ((p, p2), (q, q2), (v, v2), (w, w2)):
        assert (a - b).abs().max() <= ROUND_TRIP
    x3, xv3 = pose_to_points(p2, q2, v2, w2)
    assert (x3 - x).abs().max() <= ROUND_TRIP and (xv3 - xv).abs().max() <= ROUND_TRIP


def test_quaternions_match_scipy_and_near_half_turns():
    (_, _, _), q = _random_poses(200, 1)
    half_turns = torch.tensor([[0.0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1e-9, 1, 1e-9, 0]], dtype=torch.float64)
    q = torch.cat([q, half_turns / half_turns.norm(dim=-1, keepdim=True)])
    R = quaternion_to_matrix(q)
    ref = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()
    assert np.abs(R.numpy() - ref).max() <= ROUND_TRIP
    back = matrix_to_quaternion(R)
    assert torch.minimum((back - q).abs().amax(-1), (back + q).abs().amax(-1)).max() <= ROUND_TRIP


def _state(position, quaternion, velocity=(0, 0, 0), omega=(0, 0, 0)):
    t = lambda a: torch.tensor([a], dtype=torch.float64)  # noqa: E731
    x, v = pose_to_points(t(position), t(quaternion), t(velocity), t(omega))
    return State(x, v)


def test_corner_gaps_and_jacobian_rows_against_finite_differences():
    task = build_task("Cube")
    det = task.system.detector
    (p, v, w), q = _random_poses(6, 2)
    x, xv = pose_to_points(0.05 * p, q, v, w)
    # gaps: the corners' heights, computed independently with scipy
    corners = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * HALF
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()
    world = (0.05 * p).numpy()[:, None] + np.einsum("bij,vj->bvi", R, corners)
    assert np.abs(det.gaps(x).numpy() - world[..., 2]).max() <= 1e-15
    # rows: J (B, K, 3, D) times the state's velocity is the corner's velocity in the contact frame
    J = det.jacobian(x)
    rel = torch.einsum("bkrd,bd->bkr", J, xv.reshape(6, -1))
    h = 1e-6
    vel = (det_points(det, x + h * xv) - det_points(det, x - h * xv)) / (2 * h)  # (B, K, 3) world velocity
    frame = det.kinds[0].frame  # (K, 3, 3) normal first
    assert (rel - torch.einsum("krd,bkd->bkr", frame, vel)).abs().max() <= 1e-8


def det_points(det, x):
    """World corners (B, K, 3) from the kind's weights (independent of the Jacobian code path)."""
    kind = det.kinds[0]
    return (kind.weights[None, :, :, None] * x[:, kind.pts]).sum(2)


def test_a_cube_resting_on_a_face_stays_at_rest():
    task = build_task("Cube")
    sim = simulator_for(task, "lagrangian", 0.0, None)
    xs, vs, _ = sim.rollout(_state((0.0, 0.0, HALF), (1.0, 0.0, 0.0, 0.0)), task.params, task.dt, 150)
    p, q, v, w = points_to_pose(xs[0], vs[0])
    # settles at the depth of the velocity-level compensation (≈ g dt² / 2 / compensation), no deeper, no drift
    assert (HALF - p[:, 2]).max() <= 0.6e-3
    assert p[:, :2].abs().max() <= 1e-6
    angle = 2 * torch.arccos(q[:, 0].abs().clamp(max=1.0))
    assert angle.max() <= 1e-5
    assert w.norm(dim=-1).max() <= 1e-4


def test_free_flight_conserves_energy_and_a_flat_drop_rebounds_with_e():
    task = build_task("Cube", {"contact": {"mu": [0.0]}})
    sim = simulator_for(task, "lagrangian", 0.0, None)
    # a spinning toss high above the table: energy conserved (RK4 with constraints, no contact)
    s = _state((0.0, 0.0, 1.0), (0.9, 0.1, 0.3, 0.2), (0.5, -0.2, 0.1), (3.0, -2.0, 5.0))
    xs, vs, _ = sim.rollout(s, task.params, task.dt, 40)
    energy = task.system.energy(task.params, xs[0], vs[0])
    assert (energy - energy[0]).abs().max() <= 1e-7 * energy[0].abs()
    # dropped flat at 1 m/s: four corners hit at once; the Poisson rebound is e times the impact speed
    s = _state((0.0, 0.0, HALF + 0.002), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    xs, vs, _ = sim.rollout(s, task.params, task.dt, 3)
    p, _, v, w = points_to_pose(xs[0], vs[0])
    e = float(task.params.e[0])
    impact = (1.0 + 2 * 9.81 * 0.002) ** 0.5  # speed when the face reaches the table
    up = v[1:, 2].max()
    assert up == pytest.approx(e * impact, abs=0.07)  # gravity acts over the rest of the frame (≤ g dt = 0.066)
    assert w.norm(dim=-1).max() <= 1e-9 and v[:, :2].abs().max() <= 1e-9
