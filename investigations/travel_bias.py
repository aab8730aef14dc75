"""Where along a toss a model's position error builds up: the signed error of the predicted centre along each
toss's recorded travel (its horizontal displacement from the first frame to the last) and across it, at given
frames and at the last frame, in % of the box's width, mean and median over the tosses.

A model that loses too much speed at the impacts is behind (negative) after them; one that slides too freely ends
ahead (positive). The error across the travel (positive: to the left) is also split by the sign of each toss's
first spin about the vertical and about its travel direction. Reads an evaluation's predictions.npz
(``diffcontact evaluate``) and the dataset it scored.

    python investigations/travel_bias.py runs/cubetoss-com/seed1/eval data/CubeToss --split test
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
from pathlib import Path

import numpy as np

from diffcontact.eval.tosses import recorded_tosses
from diffcontact.systems.poses import rotate

FRAMES = (10, 20, 30, 40, 60, 80, 120)


def _tosses(predicted: dict, recorded):
    """Per toss: its first frame's index into ``recorded``, the recorded and predicted centres (T, 3) m, and the unit
    horizontal directions along its travel (first frame to last) and across it (to the left), (2,) each."""
    for i in range(len(recorded.toss_id)):
        a, b = recorded.offsets[i], recorded.offsets[i + 1]
        rec, pred = recorded.position[a:b], predicted["position"][predicted["offsets"][i] : predicted["offsets"][i + 1]]
        travel = rec[-1, :2] - rec[0, :2]
        along = travel / max(float(np.linalg.norm(travel)), 1e-12)
        yield a, rec, pred, along, np.array([-along[1], along[0]])


def travel_bias(predicted: dict, recorded, width: float, frames=FRAMES) -> dict:
    """{"frame N": {"along_mean", "along_median", "across_mean", "tosses"}, ..., "last": {...}} of the predictions
    (position (F, 3) m, offsets) against the recorded tosses (``Tosses``, the same tosses in the same order)."""
    at: dict[str, list[tuple[float, float]]] = {f"frame {f}": [] for f in frames} | {"last": []}
    for _, rec, pred, along, across in _tosses(predicted, recorded):
        for key, f in [*((f"frame {f}", f) for f in frames), ("last", len(rec) - 1)]:
            if f < len(rec):
                d = (pred[f, :2] - rec[f, :2]) / width * 100.0
                at[key].append((float(d @ along), float(d @ across)))
    out = {}
    for key, pairs in at.items():
        if pairs:
            values = np.asarray(pairs)
            out[key] = {
                "along_mean": float(values[:, 0].mean()),
                "along_median": float(np.median(values[:, 0])),
                "across_mean": float(values[:, 1].mean()),
                "tosses": len(values),
            }
    return out


def across_by_spin(predicted: dict, recorded, width: float) -> dict:
    """The last frame's error across the travel (% of the width) split by the sign of each toss's first spin (table
    frame) about the vertical and about its travel direction: {"about the vertical": {"spin > 0": {"across_mean",
    "tosses"}, "spin < 0": {...}, "correlation": Pearson's r of that error with the spin}, "about the travel": ...}."""
    across, spins = [], []
    for a, rec, pred, along, normal in _tosses(predicted, recorded):
        across.append(float((pred[-1, :2] - rec[-1, :2]) @ normal / width * 100.0))
        omega = rotate(recorded.quaternion[a : a + 1], recorded.omega[a][None])[0, 0]  # (body to table)
        spins.append((float(omega[2]), float(omega[:2] @ along)))
    across_a, spin_a = np.asarray(across), np.asarray(spins)
    out: dict = {}
    for column, about in enumerate(("about the vertical", "about the travel")):
        spin, part = spin_a[:, column], {}
        for key, mask in (("spin > 0", spin > 0), ("spin < 0", spin < 0)):
            if mask.any():
                part[key] = {"across_mean": float(across_a[mask].mean()), "tosses": int(mask.sum())}
        out[about] = part | {"correlation": float(np.corrcoef(across_a, spin)[0, 1])}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("eval_dir", help="an evaluation folder with predictions.npz")
    parser.add_argument("data", help="the imported dataset it scored")
    parser.add_argument("--split", default="test")
    args = parser.parse_args()
    recorded, request = recorded_tosses(args.data, args.split)
    with np.load(Path(args.eval_dir) / "predictions.npz") as saved:
        predicted = {k: saved[k] for k in saved.files}
    if not np.array_equal(predicted["toss_id"], recorded.toss_id):
        raise SystemExit(f"{args.eval_dir}: its tosses are not the {args.split} tosses of {args.data}")
    width = 2.0 * float(request["half_extents_m"][0])
    out = travel_bias(predicted, recorded, width)
    out["across, by first spin"] = across_by_spin(predicted, recorded, width)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
