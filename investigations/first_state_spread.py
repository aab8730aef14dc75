"""How far the uncertainty of a measured toss's first state moves its whole-toss prediction.

A rollout of a real toss starts from the free-flight fit of its first frames (``data.measured.first_states``). The
recorded poses' noise is estimated from the residuals of those fits (pooled over the split's tosses with at least
6 free-flight frames); the fitted state's covariance follows from least squares.  Each toss's first state is drawn
``--draws`` times from it (and its recorded first rotation perturbed by the rotation noise), every draw is rolled
out over the whole toss with the task file's (nominal) values, and the script reports, in % of the block width
(position error as ``diffcontact evaluate`` scores it):

- the mean error of the unperturbed rollout against the recording;
- the mean distance of the drawn rollouts from the unperturbed one, and between two drawn rollouts: what the first
  state's own uncertainty accounts for;
- the mean error of the drawn rollouts against the recording, and of the best draw of each toss;
- the final face: on how many tosses the unperturbed rollout ends on the recorded face, and for those where it does
  not, in how many draws it does (a toss that some draws bring to the recorded face sits near a boundary between
  outcomes that its first state's uncertainty crosses).

    python investigations/first_state_spread.py data/CubeToss --split val --draws 6
    python investigations/first_state_spread.py data/CubeToss --split test --run runs/CubeToss/CM-CD-CLNN/seed0
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json

import numpy as np
import torch
from com_offset import on_table, resting_frames, resting_tilt  # (the script beside this one)

from diffcontact.data import measured
from diffcontact.eval.loading import load_run
from diffcontact.eval.pose_metrics import face_down
from diffcontact.eval.rollouts import predict
from diffcontact.eval.tosses import recorded_tosses
from diffcontact.models.model import known_model
from diffcontact.systems.poses import (
    hat,
    matrix_to_quaternion,
    points_to_pose,
    pose_to_points,
    quaternion_to_matrix,
    rotation_vector,
)
from diffcontact.systems.registry import build_task


def pose_noise(tosses, table_height, half_extents) -> tuple[float, float]:
    """Position (m) and rotation (rad) noise: the residual spread of the free-flight fits of ``first_states``."""
    R = quaternion_to_matrix(torch.from_numpy(tosses.quaternion))
    res_p, res_r = [], []
    frames = measured.flight_frames(tosses, table_height, half_extents)
    for start, m in zip(tosses.offsets[:-1].tolist(), frames, strict=True):
        if m < 6:
            continue
        t = np.arange(m) * tosses.dt
        X = np.stack([np.ones(m), t], 1)
        lifted = tosses.position[start : start + m] + np.outer(0.5 * measured.GRAVITY * t**2, [0.0, 0.0, 1.0])
        coef, *_ = np.linalg.lstsq(X, lifted, rcond=None)
        res_p.append((lifted - X @ coef) * np.sqrt(m / (m - 2)))
        turns = rotation_vector(matrix_to_quaternion(R[start].mT @ R[start : start + m])).numpy()
        res_r.append((turns - np.outer(t, t @ turns / (t @ t)))[1:])  # (frame 0 is fitted exactly)
    return float(np.concatenate(res_p).std(0).mean()), float(np.concatenate(res_r).std(0).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="an imported dataset folder (diffcontact import contactnets)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--draws", type=int, default=6)
    parser.add_argument("--task", default="CubeToss")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--run", help="a trained run's model instead of the task file's nominal values")
    parser.add_argument(
        "--tilt-correction",
        type=float,
        default=0.0,
        help="turn each first rotation back by this multiple of the tracking's tilt where the cube is, as fitted on "
        "the resting frames (com_offset.py --faces)",
    )
    parser.add_argument(
        "--rotation-sd", type=float, help="deg: draw the first rotation with this spread instead of the pose noise's"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)

    tosses, request = recorded_tosses(args.data, args.split)
    height, half = request["table_height_m"], request["half_extents_m"]
    sigma_p, sigma_r = pose_noise(tosses, height, half)
    t = np.arange(measured.FLIGHT_FRAMES) * tosses.dt
    X = np.stack([np.ones_like(t), t], 1)
    chol = np.linalg.cholesky(sigma_p**2 * np.linalg.inv(X.T @ X))  # of (position, velocity) per axis
    sigma_w = sigma_r / np.sqrt(t @ t)

    p0, v0, w0 = measured.first_states(tosses, height, half)
    q0 = tosses.quaternion[tosses.offsets[:-1]]
    if args.tilt_correction:
        _, fit = resting_tilt(*resting_frames(args.data))
        tilt = args.tilt_correction * on_table(p0[:, :2]) @ fit  # (n, 2), rad
        back = torch.from_numpy(np.column_stack([tilt[:, 1], -tilt[:, 0], np.zeros(len(tilt))]))  # the turn undone
        q0 = matrix_to_quaternion(torch.linalg.matrix_exp(hat(back)) @ quaternion_to_matrix(torch.from_numpy(q0)))
        q0 = q0.numpy()
    n, K, T = len(p0), args.draws, int(tosses.lengths.max())
    rng = np.random.default_rng(args.seed)
    pv = np.einsum("ij,knjc->knic", chol, rng.standard_normal((K, n, 2, 3)))
    turn_sd = np.radians(args.rotation_sd) if args.rotation_sd is not None else sigma_r
    turn = torch.from_numpy(rng.standard_normal((K, n, 3)) * turn_sd)
    q = matrix_to_quaternion(quaternion_to_matrix(torch.from_numpy(q0)) @ torch.linalg.matrix_exp(hat(turn))).numpy()
    draws = (p0 + pv[:, :, 0], q, v0 + pv[:, :, 1], w0 + rng.standard_normal((K, n, 3)) * sigma_w)
    central = (p0[None], q0[None], v0[None], w0[None])

    net = load_run(args.run).net if args.run else known_model(build_task(args.task))
    keep = np.arange(T)[None] < tosses.lengths[:, None]

    last = tosses.lengths - 1
    recorded_face = face_down(tosses.quaternion[tosses.offsets[1:] - 1])

    def rollout(p, q, v, w) -> tuple[np.ndarray, np.ndarray]:
        """(k, n, ...) first states -> (k, n, T, 3) predicted centres (m) and (k, n) final faces."""
        arrays = (p - [0.0, 0.0, height], q, v, w)
        x, xv = pose_to_points(*(torch.from_numpy(np.ascontiguousarray(a).reshape(-1, a.shape[-1])) for a in arrays))
        x_hat, v_hat = predict(net, x, xv, T)
        position, quaternion, _, _ = points_to_pose(x_hat.double().flatten(0, 1), v_hat.double().flatten(0, 1))
        final = quaternion.numpy().reshape(p.shape[0], n, T, 4)[:, np.arange(n), last]
        faces = face_down(final.reshape(-1, 4)).reshape(p.shape[0], n)
        return position.numpy().reshape(p.shape[0], n, T, 3) + [0.0, 0.0, height], faces

    def error(a, b) -> np.ndarray:  # (..., n, T, 3) -> (..., n) mean over each toss's frames, % of the width
        e = np.linalg.norm(a - b, axis=-1) / (2 * half[0]) * 100
        return (e * keep).sum(-1) / tosses.lengths

    recorded = np.zeros((n, T, 3))
    for i in range(n):
        recorded[i, : tosses.lengths[i]] = tosses.position[tosses.frames_of(i)]
    (centre, centre_face), (drawn, drawn_faces) = rollout(*central), rollout(*draws)
    centre = centre[0]
    pairs = [error(drawn[a], drawn[b]).mean() for a in range(K) for b in range(a + 1, K)]
    same = np.concatenate([centre_face, drawn_faces]) == recorded_face  # (1 + K, n): unperturbed, then the draws
    against = error(drawn, recorded)
    result = {
        "split": args.split,
        "tosses": n,
        "draws": K,
        "pose_noise": {"position_mm": sigma_p * 1e3, "rotation_deg": float(np.degrees(sigma_r))},
        "first_state_sd": {
            "position_mm": float(chol[0, 0] * 1e3),
            "velocity_m_s": float(np.hypot(chol[1, 0], chol[1, 1])),
            "omega_rad_s": float(sigma_w),
            "rotation_deg": float(np.degrees(turn_sd)),
        },
        "position_error_pct": {
            "unperturbed_vs_recorded": float(error(centre, recorded).mean()),
            "drawn_vs_unperturbed": float(error(drawn, centre[None]).mean()),
            "drawn_vs_drawn": float(np.mean(pairs)),
            "drawn_vs_recorded": float(against.mean()),
            "best_draw_vs_recorded": float(against.min(0).mean()),
        },
    }
    result["final_face"] = {
        "unperturbed_on_recorded_face": int(same[0].sum()),
        "draws_on_recorded_face_where_unperturbed_is_not": {
            int(tosses.toss_id[i]): f"{int(same[1:, i].sum())} of {K}" for i in np.flatnonzero(~same[0])
        },
        "tosses_where_some_draws_differ_from_the_unperturbed": int((same[1:] != same[:1]).any(0).sum()),
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
