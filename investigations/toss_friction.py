"""What friction the recorded tosses show: in flat sliding, and in the first impact, against the exact model's.

Two measurements from the recorded poses of a split of an imported dataset (``diffcontact import contactnets``),
made the same way on the exact model's whole-toss rollouts (the task file's values, or ``--mu``/``--e``, from the
free-flight fit as ``evaluate`` starts them):

- **flat sliding**: frames where the four lowest corners are within 1.5 mm of the table for 13 frames around, the
  centre moving at least 3 cm/s; a parabola fitted to the centre's horizontal path over those 13 frames gives the
  speed and the deceleration along the motion. Under Coulomb friction a box sliding flat decelerates at μ g (less
  while it also spins). Reported in g by speed bin (median and interquartile range); and, between 0.1 and 0.6 m/s,
  the acceleration across the motion (to its left positive: zero for a box that slides without spinning, whatever
  its load on each corner), by the spin about the vertical and by the direction of travel;
- **the first impact**: the change of the centre's velocity across the toss's first contact (two-frame differences
  at 3 frames before and 3 after, gravity's part removed): |Δv_tangential| / Δv_normal is the ratio of the tangential
  to the normal impulse, at most μ, and equal to μ where the corner slides through the whole impact; and |Δω|, the
  change of the angular velocity (world frame, from the rotations of the frames around) across the same frames;
  and the slip of the corner lowest at the impact: how much of its horizontal velocity before it keeps after
  (1 untouched, 0 stopped, < 0 reversed), where it slid at 0.2 m/s or more.

    python investigations/toss_friction.py data/CubeToss --split val
    python investigations/toss_friction.py data/CubeToss --split val --no-model \
        --predictions runs/CubeToss/CM-CD-CLNN/seed0/eval-val/predictions.npz    # a trained model's rollouts

``--grid G.npz`` (``face_outcomes.py --save`` on the same split) also sets each toss's best μ of that grid (the
least error over its e) against the deceleration the toss slides at (median of its flat frames at 0.1–0.6 m/s),
over the tosses that end on the recorded face with the task's values: does the best μ follow the toss's friction?

    python investigations/face_outcomes.py data/CubeToss --split test --mu 0.14 0.16 0.18 0.2 0.22 --e 0 0.125 \
        --save grid.npz
    python investigations/toss_friction.py data/CubeToss --split test --no-model --grid grid.npz
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json

import numpy as np
import torch

from diffcontact.data import measured
from diffcontact.eval.rollouts import predict
from diffcontact.eval.tosses import recorded_tosses
from diffcontact.models.model import known_model
from diffcontact.systems.poses import (
    box_vertices,
    matrix_to_quaternion,
    points_to_pose,
    quaternion_to_matrix,
    rotate,
    rotation_vector,
)
from diffcontact.systems.registry import build_task

SPEED_BINS = (0.03, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8)  # m/s
SPIN_BINS = (-20.0, -2.0, -0.5, 0.5, 2.0, 20.0)  # rad/s, about the vertical
FLAT_MM, HALF_WINDOW = 1.5, 6


def flat_sliding(
    position, quaternion, dt: float, table_height: float, half_extents, flat_mm: float = FLAT_MM
) -> np.ndarray:
    """(n, 5) of the flat-sliding frames of one toss: speed (m/s), deceleration along the motion (m/s²), acceleration
    across it (m/s², to the left of the motion positive), the spin about the vertical (rad/s, counterclockwise from
    above positive) and the direction of travel (degrees from the table's x axis)."""
    heights = (position[:, None] + rotate(quaternion, box_vertices(half_extents)))[..., 2] - table_height
    flat = np.sort(heights, 1)[:, 3] < flat_mm * 1e-3
    t = np.arange(-HALF_WINDOW, HALF_WINDOW + 1) * dt
    X = np.stack([np.ones_like(t), t, 0.5 * t**2], 1)
    out = []
    for i in range(HALF_WINDOW, len(position) - HALF_WINDOW):
        if not flat[i - HALF_WINDOW : i + HALF_WINDOW + 1].all():
            continue
        coef, *_ = np.linalg.lstsq(X, position[i - HALF_WINDOW : i + HALF_WINDOW + 1, :2], rcond=None)
        speed = float(np.linalg.norm(coef[1]))
        if speed >= SPEED_BINS[0]:
            along = coef[1] / speed
            left = np.array([-along[1], along[0]])
            direction = float(np.degrees(np.arctan2(along[1], along[0])))
            out.append((speed, -float(coef[2] @ along), float(coef[2] @ left), spin(quaternion, i, dt)[2], direction))
    return np.array(out).reshape(-1, 5)


def spin(quaternion, i: int, dt: float) -> np.ndarray:
    """The world-frame angular velocity (3,) in rad/s over frames i − 1 … i + 1."""
    R = quaternion_to_matrix(torch.from_numpy(quaternion[[i - 1, i + 1]]))
    return rotation_vector(matrix_to_quaternion(R[1] @ R[0].mT)).numpy() / (2 * dt)


def first_impact(
    position, quaternion, c: int, dt: float, gravity: float, half_extents
) -> tuple[float, float, float, float, float] | None:
    """(|Δv_t| / Δv_n, Δv_n in m/s, |Δω| in rad/s, slip before in m/s, slip kept) across the first contact at frame
    ``c``, or None near the ends.  The slip is the horizontal velocity of the corner lowest at ``c``; kept is its
    velocity after along its direction before, over its speed before: 1 untouched, 0 stopped, < 0 reversed."""
    if c < 4 or c + 5 >= len(position):
        return None
    before = (position[c - 1] - position[c - 3]) / (2 * dt)
    after = (position[c + 4] - position[c + 2]) / (2 * dt)
    dn = after[2] - before[2] + gravity * 5 * dt
    dw = np.linalg.norm(spin(quaternion, c + 3, dt) - spin(quaternion, c - 2, dt))
    corners = position[:, None] + rotate(quaternion, box_vertices(half_extents))  # (frames, 8, 3)
    k = int(np.argmin(corners[c, :, 2]))
    slip0 = (corners[c - 1, k, :2] - corners[c - 3, k, :2]) / (2 * dt)
    slip1 = (corners[c + 4, k, :2] - corners[c + 2, k, :2]) / (2 * dt)
    speed = float(np.linalg.norm(slip0))
    kept = float(slip1 @ slip0) / speed**2 if speed > 0 else float("nan")
    return float(np.linalg.norm(after[:2] - before[:2]) / dn), float(dn), float(dw), speed, kept


def summary(sliding: np.ndarray, ratios: np.ndarray, gravity: float) -> dict:
    bins = {}
    for lo, hi in zip(SPEED_BINS[:-1], SPEED_BINS[1:], strict=True):
        d = sliding[(sliding[:, 0] >= lo) & (sliding[:, 0] < hi), 1] / gravity
        if len(d):
            q25, q50, q75 = np.percentile(d, [25, 50, 75])
            bins[f"{lo}-{hi} m/s"] = {
                "frames": len(d),
                "median_g": round(q50, 3),
                "iqr_g": [round(q25, 3), round(q75, 3)],
            }
    fast = sliding[(sliding[:, 0] >= 0.1) & (sliding[:, 0] < 0.6)]  # (the speeds where the deceleration is steady)
    lateral, spin_z = fast[:, 2] / gravity, fast[:, 3]
    by_spin = {}
    for lo, hi in zip(SPIN_BINS[:-1], SPIN_BINS[1:], strict=True):
        k = (spin_z >= lo) & (spin_z < hi)
        if k.any():
            by_spin[f"{lo:g} to {hi:g} rad/s"] = {
                "frames": int(k.sum()),
                "median_g": round(float(np.median(lateral[k])), 4),
            }
    by_direction = {}
    for lo in range(-180, 180, 45):
        k = (fast[:, 4] >= lo) & (fast[:, 4] < lo + 45)
        if k.any():
            by_direction[f"{lo} to {lo + 45} deg"] = {
                "frames": int(k.sum()),
                "along_median_g": round(float(np.median(fast[k, 1] / gravity)), 3),
                "across_median_g": round(float(np.median(lateral[k])), 4),
            }
    impacts = ratios[ratios[:, 1] > 0.5]  # (impacts of at least 0.5 m/s)
    r = impacts[:, 0]
    slipping = impacts[impacts[:, 3] > 0.2]  # (the lowest corner slipping at 0.2 m/s or more before)
    kept = slipping[:, 4]
    return {
        "flat_sliding_deceleration": bins,
        "flat_sliding_across_0.1-0.6_m_s": {
            "frames": len(fast),
            "median_g": round(float(np.median(lateral)), 4),
            "correlation_with_spin": round(float(np.corrcoef(spin_z, lateral)[0, 1]), 3),
            "by_spin": by_spin,
            "by_direction": by_direction,
        },
        "first_impact_ratio": {
            "impacts": len(r),
            "median": round(float(np.median(r)), 3),
            "p25_p75_p90": [round(float(v), 3) for v in np.percentile(r, [25, 75, 90])],
            "spin_change_median_rad_s": round(float(np.median(impacts[:, 2])), 2),
        },
        "first_impact_corner_slip": {
            "impacts": len(kept),
            "slip_before_median_m_s": round(float(np.median(slipping[:, 3])), 3),
            "kept_p10_p25_p50_p75_p90": [round(float(v), 3) for v in np.percentile(kept, [10, 25, 50, 75, 90])],
            "reversed": int((kept < 0).sum()),
            "stopped_within_0.1": int((np.abs(kept) < 0.1).sum()),
        },
    }


def best_mu_against_sliding(grid: str, tosses, height: float, half, gravity: float) -> dict:
    """Spearman's correlation of each toss's best μ in ``grid`` with its flat-sliding deceleration (see the module)."""
    from scipy.stats import spearmanr

    saved = np.load(grid)
    cells, errors = saved["cells"], saved["errors"]
    if not np.array_equal(saved["toss_id"], tosses.toss_id):
        raise SystemExit(f"{grid} holds other tosses than this split")
    nominal = build_task("CubeToss").params
    at_task = np.flatnonzero((cells[:, 0] == float(nominal.mu[0])) & (cells[:, 1] == float(nominal.e[0])))
    if not len(at_task):
        raise SystemExit(f"{grid} has no cell at the task's μ and e")
    mus = np.unique(cells[:, 0])
    best_mu = mus[np.stack([errors[cells[:, 0] == m].min(0) for m in mus]).argmin(0)]
    sliding = np.full(tosses.n, np.nan)
    for i in range(tosses.n):
        r = tosses.frames_of(i)
        s = flat_sliding(tosses.position[r], tosses.quaternion[r], tosses.dt, height, half)
        s = s[(s[:, 0] > 0.1) & (s[:, 0] < 0.6)]
        if len(s) >= 5:
            sliding[i] = np.median(s[:, 1]) / gravity
    keep = np.isfinite(sliding) & saved["same_face"][at_task[0]]
    rho = spearmanr(best_mu[keep], sliding[keep])
    by_mu = {f"{m:g}": {"tosses": int((keep & (best_mu == m)).sum()),
                        "median_sliding_g": round(float(np.median(sliding[keep & (best_mu == m)])), 3)}
             for m in mus if (keep & (best_mu == m)).any()}  # fmt: skip
    return {"tosses": int(keep.sum()), "spearman": round(float(rho.statistic), 3), "p": round(float(rho.pvalue), 3),
            "by_best_mu": by_mu}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="an imported dataset folder (diffcontact import contactnets)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--task", default="CubeToss")
    parser.add_argument("--mu", type=float, default=None, help="the model's μ (default: the task file's)")
    parser.add_argument("--e", type=float, default=None, help="the model's e (default: the task file's)")
    parser.add_argument("--no-model", action="store_true", help="measure the recording only")
    parser.add_argument("--grid", help="face_outcomes.py --save of the same split: best μ against sliding friction")
    parser.add_argument("--predictions", help="a run's predictions.npz on the same split (diffcontact evaluate)")
    parser.add_argument("--flat-mm", type=float, default=FLAT_MM, help="flat: the 4th lowest corner below this (mm)")
    args = parser.parse_args()
    torch.set_num_threads(1)

    tosses, request = recorded_tosses(args.data, args.split)
    height, half = request["table_height_m"], request["half_extents_m"]
    first_contact = measured.flight_frames(tosses, height, half)
    gravity = measured.GRAVITY

    def measure(poses) -> dict:
        sliding, ratios = [], []
        for i, (position, quaternion) in enumerate(poses):
            sliding.append(flat_sliding(position, quaternion, tosses.dt, height, half, args.flat_mm))
            ratio = first_impact(position, quaternion, first_contact[i], tosses.dt, gravity, half)
            if ratio is not None:
                ratios.append(ratio)
        return summary(np.concatenate(sliding), np.array(ratios), gravity)

    rows = [tosses.frames_of(i) for i in range(tosses.n)]
    result = {"split": args.split, "tosses": tosses.n, "recorded": measure(
        (tosses.position[r], tosses.quaternion[r]) for r in rows
    )}  # fmt: skip
    if not args.no_model:
        overrides = {"contact": {k: [v] for k, v in (("mu", args.mu), ("cor", args.e)) if v is not None}}
        task = build_task(args.task, overrides)
        x, v = measured.tosses_to_points(tosses, height, half)
        first = tosses.offsets[:-1]
        x_hat, v_hat = predict(known_model(task), torch.from_numpy(x[first]), torch.from_numpy(v[first]), max(
            int(n) for n in tosses.lengths
        ))  # fmt: skip

        def predicted():
            for i, n in enumerate(tosses.lengths):
                position, quaternion, _, _ = points_to_pose(x_hat[i, :n].double(), v_hat[i, :n].double())
                yield position.numpy() + [0.0, 0.0, height], quaternion.numpy()

        label = f"model mu {float(task.params.mu[0]):g} e {float(task.params.e[0]):g}"
        result[label] = measure(predicted())
    if args.predictions:
        with np.load(args.predictions) as saved:
            if not np.array_equal(saved["toss_id"], tosses.toss_id):
                raise SystemExit(f"{args.predictions} holds other tosses than this split")
            position, quaternion = saved["position"], saved["quaternion"]
        result[args.predictions] = measure((position[r], quaternion[r]) for r in rows)
    if args.grid:
        result["best_mu_against_sliding"] = best_mu_against_sliding(args.grid, tosses, height, half, gravity)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
