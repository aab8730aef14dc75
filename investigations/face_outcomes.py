"""Which tosses end on another face than the recorded one, and how well any μ, e, inertia of the exact model does.

For each toss of a split of an imported dataset (``diffcontact import contactnets``), this script reports:

- the recording: its final face down, how often the face down changes after the first contact, and the largest
  frame-to-frame turn of the recorded rotation against the turn its recorded angular velocity gives (a jump of the
  tracking, which no model can follow, shows as a turn far above the velocity's);
- the exact model's whole-toss rollout (from the free-flight fit, as ``evaluate`` starts it) over a grid of μ, e
  and multiples of the task file's moments of inertia: the position error (% of the width, as ``evaluate`` scores
  it) and whether the last predicted frame has the recorded face down.

It prints, for the tosses that end on another face with the task's values: on how many some cell of the grid
ends on the recorded face, the mean error of the best single cell and of each toss's own best (a bound no single
value reaches), as JSON.

    python investigations/face_outcomes.py data/CubeToss --split test --mu 0.1 0.18 0.3 --e 0 0.125 0.3
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import itertools
import json

import numpy as np
import torch

from diffcontact.data import measured
from diffcontact.eval.pose_metrics import face_down, per_toss_position_error, rotation_angle
from diffcontact.eval.rollouts import predict
from diffcontact.eval.tosses import recorded_tosses
from diffcontact.models.model import known_model
from diffcontact.systems.poses import points_to_pose
from diffcontact.systems.registry import build_task


def recorded_facts(tosses, table_height: float, half_extents) -> list[dict]:
    """Per toss: final face, face changes after the first contact, largest turn between frames against ω dt (deg)."""
    first_contact = measured.flight_frames(tosses, table_height, half_extents)
    facts = []
    for i in range(len(tosses.lengths)):
        rows = tosses.frames_of(i)
        q = tosses.quaternion[rows]
        turn = np.degrees(rotation_angle(q[1:], q[:-1]))
        expected = np.degrees(np.linalg.norm(tosses.omega[rows][:-1], axis=1) * tosses.dt)
        faces = face_down(q)[first_contact[i] :]
        facts.append({
            "toss_id": int(tosses.toss_id[i]),
            "final_face": int(faces[-1]),
            "face_changes": int((np.diff(faces) != 0).sum()),
            "max_turn_deg": float(turn.max()),
            "max_excess_turn_deg": float((turn - expected).max()),
        })  # fmt: skip
    return facts


def task_value_details(tosses, position, quaternion, other, table_height: float, half_extents) -> dict:
    """With the task's values: how the face-down sequence after the first contact differs on the tosses that end on
    another face, their rotation error 5 frames after it, and where the others' last predicted centre is against
    the recorded one, along each toss's travel (its first to last recorded centre) and across it (% of the width)."""
    first_contact = measured.flight_frames(tosses, table_height, half_extents)
    width = 2.0 * float(np.asarray(half_extents)[0])
    rolls, early, along, across = [], [], [], []
    for i in range(tosses.n):
        rows = tosses.frames_of(i)
        c = first_contact[i]
        if other[i]:
            changes = [int((np.diff(face_down(q[rows][c:])) != 0).sum()) for q in (tosses.quaternion, quaternion)]
            rolls.append(changes[0] - changes[1])
            k = rows.start + min(c + 5, tosses.lengths[i] - 1)
            early.append(float(np.degrees(rotation_angle(quaternion[k : k + 1], tosses.quaternion[k : k + 1]))[0]))
        else:
            travel = tosses.position[rows.stop - 1, :2] - tosses.position[rows.start, :2]
            travel /= np.linalg.norm(travel)
            miss = (position[rows.stop - 1, :2] - tosses.position[rows.stop - 1, :2]) / width * 100
            along.append(miss @ travel)
            across.append(miss[1] * travel[0] - miss[0] * travel[1])
    return {
        "other_face_recorded_minus_predicted_face_changes": rolls,
        "other_face_rotation_error_deg_5_frames_after_contact": [round(a, 1) for a in early],
        "same_face_last_frame_miss_pct": {
            "along_travel_mean": float(np.mean(along)),
            "along_travel_mean_abs": float(np.mean(np.abs(along))),
            "across_travel_mean_abs": float(np.mean(np.abs(across))),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="an imported dataset folder (diffcontact import contactnets)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--task", default="CubeToss")
    parser.add_argument("--mu", type=float, nargs="+", default=[0.1, 0.18, 0.3])
    parser.add_argument("--e", type=float, nargs="+", default=[0.0, 0.125, 0.3])
    parser.add_argument("--moments", type=float, nargs="+", default=[1.0], help="multiples of the task's moments")
    parser.add_argument("--save", help="an .npz for every cell's per-toss errors and final-face flags")
    args = parser.parse_args()
    torch.set_num_threads(1)

    tosses, request = recorded_tosses(args.data, args.split)
    height, half = request["table_height_m"], request["half_extents_m"]
    facts = recorded_facts(tosses, height, half)
    x0, v0 = measured.tosses_to_points(tosses, height, half)
    first = tosses.offsets[:-1]
    x0, v0 = (torch.from_numpy(a[first]) for a in (x0, v0))
    T, last = int(tosses.lengths.max()), tosses.offsets[1:] - 1
    keep = np.concatenate([np.arange(n) for n in tosses.lengths])
    toss_of = np.repeat(np.arange(len(tosses.lengths)), tosses.lengths)

    nominal = build_task(args.task).params
    key = (float(nominal.mu.flatten()[0]), float(nominal.e.flatten()[0]), 1.0)
    moments = nominal.inertia.moments.flatten().tolist()
    grid, at_key = {}, None
    for mu, e, scale in itertools.product(args.mu, args.e, args.moments):
        body = {"moments": [scale * m for m in moments]}
        net = known_model(build_task(args.task, {"contact": {"mu": [mu], "cor": [e]}, "body": body}))
        x, v = predict(net, x0, v0, T)
        x, v = x[toss_of, keep], v[toss_of, keep]  # one predicted frame per recorded frame
        position, quaternion, _, _ = points_to_pose(x.double(), v.double())
        position = position.numpy() + [0.0, 0.0, height]
        error = per_toss_position_error(position, tosses.position, tosses.offsets, half)
        same = face_down(quaternion.numpy()[last]) == face_down(tosses.quaternion[last])
        grid[(mu, e, scale)] = (error, same)
        if (mu, e, scale) == key:
            at_key = (position, quaternion.numpy())
        print(f"mu {mu} e {e} moments x{scale}: {error.mean():.2f} %, same face {int(same.sum())} of {len(same)}",
              flush=True)  # fmt: skip

    if at_key is None:
        raise SystemExit(f"the grid must hold the task's own values mu {key[0]}, e {key[1]} and moments x1")
    other = ~grid[key][1]
    errors = np.stack([g[0] for g in grid.values()])  # (cells, tosses)
    sames = np.stack([g[1] for g in grid.values()])
    best_cell = int(errors.mean(1).argmin())
    result = {
        "split": args.split,
        "tosses": int(len(other)),
        "task_values": {"mu": key[0], "e": key[1], "error_pct": float(grid[key][0].mean())},
        "other_face_tosses": [f["toss_id"] for f, o in zip(facts, other, strict=True) if o],
        **task_value_details(tosses, *at_key, other, height, half),
        "other_face_reached_by_some_cell": int(sames[:, other].any(0).sum()),
        "best_single_cell": {"mu_e_moments": list(grid)[best_cell], "error_pct": float(errors[best_cell].mean())},
        "each_toss_own_best_pct": float(errors.min(0).mean()),
        "each_toss_own_best_pct_other_face": float(errors[:, other].min(0).mean()) if other.any() else None,
        "recorded": {
            "face_changes_after_contact_median": float(np.median([f["face_changes"] for f in facts])),
            "max_excess_turn_deg_other_face": [round(f["max_excess_turn_deg"], 1) for f, o in zip(facts, other) if o],
            "max_excess_turn_deg_same_face_median": float(
                np.median([f["max_excess_turn_deg"] for f, o in zip(facts, other) if not o])
            ),
        },
    }
    if args.save:
        np.savez(args.save, cells=np.array(list(grid)), errors=errors, same_face=sames, toss_id=tosses.toss_id)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
