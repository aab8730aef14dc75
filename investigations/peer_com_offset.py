"""The MuJoCo and Bullet peers at their nominal parameters with the cube's centre of mass off its box centre.

Our own model predicts the real tosses best with the centre of mass 9 mm along the body's +z. This scores each
peer's unfitted nominal parameters (as ``peers fit`` scores "nominal") on the validation and test tosses of the
standard split (``run_fit``'s: 0.8/0.1/0.1, seed 0, the table from the training split's resting frames, rollouts
from the fitted first states) with the centre of mass at each ``--com`` (mm, body frame), and the paired difference
toss by toss of the position error of the second offset minus the first (the first offset is the reference).

    python investigations/peer_com_offset.py /work/shared/data/contactnets_cube_tosses.npz
    python investigations/peer_com_offset.py SOURCE --engine mujoco --com 0 0 0 --com 0 0 9 --out com.json
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json

from diffcontact.data.tosses import read_tosses
from diffcontact.eval.pose_metrics import box_toss_metrics, paired_difference, per_toss_position_error
from diffcontact.peers import ENGINES, load_engine
from diffcontact.peers.cube import COM_NAMES, HALF_EXTENT, nominal
from diffcontact.peers.fit import peer_tosses

KEYS = ("position_error_pct", "rotation_error_deg", "penetration_pct")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", help="the tosses (a ContactNets .npz or a folder of K.pt files)")
    parser.add_argument("--engine", action="append", choices=list(ENGINES), help="repeat (default: both)")
    parser.add_argument("--com", type=float, nargs=3, action="append", help="mm, body frame; repeat")
    parser.add_argument("--out", help="also write the results (with the per-toss errors) to this JSON file")
    args = parser.parse_args()
    offsets = args.com or [[0.0, 0.0, 0.0], [0.0, 0.0, 9.0], [0.0, 0.0, 6.0]]
    half = [HALF_EXTENT] * 3

    setting = peer_tosses(read_tosses(args.source))  # (run_fit's defaults)
    table_height = setting.table_height
    results = []
    print("| engine | split | COM (mm) | position % | rotation ° | penetration % | paired Δ position % vs first |")
    print("|---|---|---|---|---|---|---|")
    for name in args.engine or list(ENGINES):
        engine = load_engine(name)
        for split in ("val", "test"):
            recorded = setting.part(split)
            starts = setting.starts(recorded)
            reference = None
            for com in offsets:
                params = nominal(engine.PARAMETERS) | {n: 1e-3 * c for n, c in zip(COM_NAMES, com)}
                position, quaternion = engine.simulate(starts, params, table_height)
                m = box_toss_metrics(position, quaternion, recorded.position, recorded.quaternion, recorded.offsets,
                                     half, table_height)  # fmt: skip
                errors = per_toss_position_error(position, recorded.position, recorded.offsets, half)
                paired = None if reference is None else paired_difference(errors, reference)
                reference = errors if reference is None else reference
                results.append({"engine": name, "split": split, "com_mm": com, **{k: m[k] for k in KEYS},
                                "paired_vs_first": paired, "per_toss_position_error": errors.tolist()})  # fmt: skip
                d = "" if paired is None else f"{paired['mean']:+.2f} [{paired['lo']:+.2f}, {paired['hi']:+.2f}]"
                print(f"| {name} | {split} ({recorded.n}) | {', '.join(f'{c:g}' for c in com)} | "
                      f"{m['position_error_pct']:.2f} | {m['rotation_error_deg']:.2f} | {m['penetration_pct']:.3f} | "
                      f"{d} |", flush=True)  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"source": args.source, "table_height_m": table_height, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
