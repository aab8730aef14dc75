"""The nominal model with its centre of mass off the box's centre (an experiment on the real cube tosses).

The recorded cube ends its tosses on its +z face (body frame) in 124 of 470 tosses, where a symmetric cube would
end on each face in about 78 (χ² p 5e-7); it starts them on each face about equally (p 0.31). A cube whose mass
sits nearer one face would do that. This script scores the nominal model of the task file (μ, e, mass, moments) on
a split's whole tosses (as ``evaluate`` does) with its centre of mass at ``--offset`` (body frame, mm) from the
box's centre (the task file's ``body.centre_of_mass``, which a trained model learns).

    python investigations/com_offset.py data/CubeToss --split val --offset 0 0 3
    python investigations/com_offset.py data/CubeToss --faces     # the final faces of every toss, and resting heights
    python investigations/com_offset.py --paired A.json B.json   # two saved outputs' paired difference, toss by toss
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
from collections import Counter

import numpy as np
import torch
from scipy.stats import chisquare

from diffcontact.eval import pose_metrics
from diffcontact.eval.pose_metrics import paired_difference, per_toss_position_error
from diffcontact.eval.tosses import predict_tosses, recorded_tosses, score_tosses
from diffcontact.models.model import known_model
from diffcontact.systems.poses import rotate
from diffcontact.systems.registry import build_task

FACES = ("-x", "+x", "-y", "+y", "-z", "+z")  # (the numbering of pose_metrics.face_down)


def face_down(quaternion: np.ndarray) -> list[str]:
    """The body face that points most nearly down, named as in ``FACES``, for each quaternion (n, 4), w first."""
    return [FACES[i] for i in pose_metrics.face_down(quaternion)]


def resting_frames(data) -> tuple[np.ndarray, np.ndarray]:
    """The last frame of every toss of every split of the dataset ``data``: quaternions (n, 4), positions (n, 3)."""
    q, p = [], []
    for split in ("train", "val", "test"):
        tosses, _ = recorded_tosses(data, split)
        q.append(tosses.quaternion[tosses.offsets[1:] - 1])
        p.append(tosses.position[tosses.offsets[1:] - 1])
    return np.concatenate(q), np.concatenate(p)


def on_table(xy: np.ndarray) -> np.ndarray:
    """The rows [1, x, y] (n, 3) of a linear fit on where the cube is on the table, x, y (n, 2) in m."""
    return np.column_stack([np.ones(len(xy)), xy])


def resting_tilt(quaternion: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tilt (n, 2) of each resting cube's upward axis (its table-x and -y parts, rad to first order) and its
    linear fit on where the cube rests, (3, 2): tilt ≈ [1, x, y] @ fit (x, y in m)."""
    axes = rotate(quaternion, np.eye(3))  # (n, 3, 3): the body's x, y, z axes in the table frame
    rows = np.arange(len(axes))
    vertical = np.abs(axes[..., 2]).argmax(1)
    up = axes[rows, vertical] * np.sign(axes[rows, vertical, 2])[:, None]
    tilt = up[:, :2]
    fit, *_ = np.linalg.lstsq(on_table(position[:, :2]), tilt, rcond=None)
    return tilt, fit


def resting_poses(quaternion: np.ndarray, position: np.ndarray) -> dict:
    """What the tosses' last frames (quaternion (n, 4), position (n, 3) in m above the table) say of the tracking.

    A tracked centre off the cube's geometric centre along a body axis would rest higher on one face of that axis
    than on the other (a centre of mass off it would not change the resting height). A cube resting flat on a flat
    table has its upward axis vertical: the tilt of that axis, in the table's frame, is the tracking's error of
    orientation or the table's slope where the cube rests, and the second would follow where it rests."""
    faces = np.array(face_down(quaternion))
    tilt, coef = resting_tilt(quaternion, position)
    X = on_table(position[:, :2])
    r2 = 1 - ((tilt - X @ coef) ** 2).sum(0) / ((tilt - tilt.mean(0)) ** 2).sum(0)
    return {
        "all, last: centre height above the table, median mm": {
            f: round(1e3 * float(np.median(position[faces == f, 2])), 3) for f in FACES
        },
        "all, last: tilt of the upward axis, median deg": round(float(np.degrees(np.median(np.hypot(*tilt.T)))), 3),
        "all, last: tilt's table-x and -y parts against the resting x, y": {
            "deg per m (rows: x part, y part; columns: x, y)": np.degrees(coef[1:].T).round(2).tolist(),
            "r2": r2.round(3).tolist(),
            "resting x, y range m": [
                position[:, :2].min(0).round(3).tolist(),
                position[:, :2].max(0).round(3).tolist(),
            ],
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", help="an imported dataset folder (diffcontact import contactnets)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--task", default="CubeToss")
    parser.add_argument("--offset", type=float, nargs=3, default=[0.0, 0.0, 0.0], help="mm, body frame")
    parser.add_argument("--faces", action="store_true", help="count the final faces of every split's tosses")
    parser.add_argument("--paired", nargs=2, metavar="JSON", help="two outputs of this script on the same split")
    args = parser.parse_args()
    torch.set_num_threads(1)

    if args.paired:
        a, b = (json.load(open(f)) for f in args.paired)
        print(json.dumps(paired_difference(a["per_toss_position_error"], b["per_toss_position_error"])))
        return

    if args.faces:
        result = {}
        for split in ("train", "val", "test"):
            tosses, _ = recorded_tosses(args.data, split)
            last = face_down(tosses.quaternion[tosses.offsets[1:] - 1])
            first = face_down(tosses.quaternion[tosses.offsets[:-1]])
            result[split] = {"last": {f: last.count(f) for f in FACES}, "first": {f: first.count(f) for f in FACES}}
        for when in ("last", "first"):
            counts = [sum(result[s][when][f] for s in ("train", "val", "test")) for f in FACES]
            result[f"all, {when}: chi-square p"] = float(chisquare(counts).pvalue)
        result |= resting_poses(*resting_frames(args.data))
        print(json.dumps(result, indent=1))
        return

    task = build_task(args.task, {"body": {"centre_of_mass": [1e-3 * o for o in args.offset]}})
    net = known_model(task)
    predicted = predict_tosses(net, args.data, args.split)
    metrics = score_tosses(predicted, args.data, args.split)
    tosses, request = recorded_tosses(args.data, args.split)
    last = tosses.offsets[1:] - 1
    recorded, ended = face_down(tosses.quaternion[last]), face_down(predicted["quaternion"][last])
    faces = {"predicted": dict(Counter(ended)), "recorded": dict(Counter(recorded))}
    errors = per_toss_position_error(predicted["position"], tosses.position, tosses.offsets, request["half_extents_m"])
    print(json.dumps({"settings": vars(args), "metrics": metrics, "final_faces": faces,
                      "per_toss_position_error": errors.tolist()}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
