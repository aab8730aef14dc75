"""Two or more methods' predictions of the same measured tosses, set against one another toss by toss.

The per-toss position error of the reference's predictions (several: each toss's mean over them, such as a
model's seeds) minus each other's (mean over tosses, % of the width,
with a seeded 95 % bootstrap interval: ``eval.tosses.paired_position_errors``). Predictions are the
``predictions.npz`` that ``diffcontact evaluate`` and ``diffcontact peers fit`` write.

    python investigations/paired_tosses.py data/CubeToss runs/CubeToss/CM-CD-CLNN/seed0/eval/predictions.npz \\
        bullet=runs/peers/bullet/predictions.npz mujoco=runs/peers/mujoco/predictions.npz
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json

from diffcontact.eval.tosses import paired_position_errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="the imported dataset the predictions were made on")
    parser.add_argument(
        "reference", help="the reference's predictions.npz; several, comma-separated: each toss's mean over them"
    )
    parser.add_argument("others", nargs="+", metavar="NAME=NPZ", help="each other method's predictions.npz")
    parser.add_argument("--split", default="test")
    args = parser.parse_args()
    others = dict(o.split("=", 1) if "=" in o else (o, o) for o in args.others)
    reference = args.reference.split(",")
    print(json.dumps(paired_position_errors(args.data, reference, others, args.split), indent=1))


if __name__ == "__main__":
    main()
