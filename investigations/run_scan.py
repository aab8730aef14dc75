"""A trained run's whole-toss errors with one of its learned values changed, the rest of the model as trained, scored
on a split's whole tosses as ``evaluate`` scores them. For μ, what ``train/calibrate.py`` searches, laid out on a
grid (docs/real_data.md, "How far μ sets the slide"); for the centre of mass and the moments, whether a calibration
of them would gain too (docs/results.md, "Real data"); rounded edges (docs/real_data.md, "What the model does not
fit").

    python investigations/run_scan.py runs/cubetoss-com/seed0 data/CubeToss --split train --mu 0.166 0.170 0.174
    python investigations/run_scan.py runs/cubetoss-com/seed1 data/CubeToss --split val --offset -0.004 0 0.004
    python investigations/run_scan.py runs/cubetoss-cal/seed1 data/CubeToss --split val --com-z -0.0015 0 0.0015
    python investigations/run_scan.py runs/cubetoss-cal/seed1 data/CubeToss --split val --moments-scale 0.9 1.1
    python investigations/run_scan.py runs/cubetoss-com/seed0 data/CubeToss --split val --checkpoint last.ckpt
    python investigations/run_scan.py runs/CubeToss/CM-CD-CLNN/seed0 data/CubeToss --split val --corner-radius 0 0.002
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import math
import time
from pathlib import Path

import torch

from diffcontact.eval.loading import load_run
from diffcontact.eval.tosses import predict_tosses, score_tosses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a trained run of a measured dataset")
    parser.add_argument("data", help="its imported dataset folder")
    parser.add_argument("--split", default="val")
    parser.add_argument("--checkpoint", default=None, help="another of the run's checkpoints (a file in checkpoints/)")
    values = parser.add_mutually_exclusive_group()
    values.add_argument("--mu", type=float, nargs="+", help="values of μ")
    values.add_argument("--offset", type=float, nargs="+", help="values added to the run's μ")
    values.add_argument("--com-z", type=float, nargs="+", help="m added to the centre of mass along the body's z")
    values.add_argument("--moments-scale", type=float, nargs="+", help="factors of the three second moments")
    values.add_argument(
        "--corner-radius",
        type=float,
        nargs="+",
        help="m: the box's edges rounded (the corners drawn in by r and every gap less r: the box grown by a sphere)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    run = Path(args.run)
    net = load_run(run, checkpoint=run / "checkpoints" / args.checkpoint if args.checkpoint else None).net
    p = net.params
    if args.corner_radius:
        rounded(net, args)
        return
    if args.com_z or args.moments_scale:
        raw = p.com_raw if args.com_z else p.log_moments
        if args.com_z:  # (com = com_raw × a fixed scale: its value per unit of com_raw)
            with torch.no_grad():
                per_raw = float(p.inertia.com[0, 2] / p.com_raw[0, 2])
            moves = [(dz, (0, 2), dz / per_raw) for dz in args.com_z]
        else:
            moves = [(f, (0, slice(None)), math.log(f)) for f in args.moments_scale]
    else:
        raw = p.mu_raw  # (the projected μ: μ itself)
        trained = float(raw[0].detach())
        mus = args.mu or [trained + o for o in args.offset or [0.0]]
        moves = [(mu, (0,), mu - trained) for mu in mus]
    start = raw.detach().clone()
    rows = []
    for value, where, step in moves:
        started = time.perf_counter()
        with torch.no_grad():
            raw.copy_(start)
            raw[where] += step
        m = score_tosses(predict_tosses(net, args.data, args.split), args.data, args.split)
        rows.append({"value": value, "seconds": time.perf_counter() - started} | m)
        position, rotation = m["position_error_pct"], m["rotation_error_deg"]
        print(f"{value:.4g}: position {position:.2f} %, rotation {rotation:.2f}°", flush=True)
    record = {"run": args.run, "split": args.split, "checkpoint": args.checkpoint, "rows": rows}
    learned = {"mu": p.mu.detach().tolist(), "centre_of_mass_m": p.inertia.com.detach().tolist()}
    print(json.dumps(record | learned, indent=1))


def rounded(net, args) -> None:
    """Score the run with its box's edges rounded by each radius r: the 8 corners at (a − r) of their half-extents
    and every gap less r, which is the gap of the box grown by a sphere of radius r to a plane (the face-down
    resting height unchanged; friction still acts at the drawn-in corner, r below the rounded contact point)."""
    (kind,) = net.simulator.system.detector.kinds
    weights, offset = kind.weights.clone(), kind.c.clone()
    half = weights[:, 1:].abs().amax(0)  # (3,) the half-extents in the body points' units
    rows = []
    for r in args.corner_radius:
        started = time.perf_counter()
        vertex = weights[:, 1:] * (1 - r / half)
        kind.weights = torch.cat([1.0 - vertex.sum(-1, keepdim=True), vertex], dim=-1)
        kind.c = offset - r
        m = score_tosses(predict_tosses(net, args.data, args.split), args.data, args.split)
        rows.append({"corner_radius_m": r, "seconds": time.perf_counter() - started} | m)
        print(f"r {r * 1000:.2f} mm: position {m['position_error_pct']:.2f} %, rotation {m['rotation_error_deg']:.2f}°")
    kind.weights, kind.c = weights, offset
    print(json.dumps({"run": args.run, "split": args.split, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
