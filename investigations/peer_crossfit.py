"""Whether a peer's fit found its best parameters: every fit's parameters scored on one fit's training tosses.

A fit (``diffcontact peers fit``, or a cell of the toss sweep) minimises its objective over its own training
tosses. If the parameters that another fit found (on other tosses of the same split) score lower on those tosses,
the search stopped short of the best it could have found. For each ``fitted.json`` given, this rolls out its
parameters over the training tosses of the first one (the tosses in its ``train_toss_id``, the table from the
training split's resting frames, rollouts from the fitted first states, as ``run_fit`` does) and prints the
objective and its two terms, as JSON lines.

    python investigations/peer_crossfit.py contactnets_cube_tosses.npz runs/sweep-com/peers/N64/mujoco/fitted.json \
        runs/sweep-com/peers/N32/mujoco/fitted.json runs/peers-com/mujoco/fitted.json
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json

import numpy as np

from diffcontact.data.tosses import read_tosses
from diffcontact.peers import load_engine
from diffcontact.peers.fit import peer_tosses, score


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", help="the tosses the fits were made on (a ContactNets .npz or folder of K.pt)")
    parser.add_argument("fitted", nargs="+", help="fitted.json files of one engine; the first one's tosses are used")
    args = parser.parse_args()
    fits = [json.loads(open(path).read()) for path in args.fitted]
    reference = fits[0]
    if len({f["engine"] for f in fits}) != 1:
        raise SystemExit("the fits are of different engines")
    setting = peer_tosses(read_tosses(args.source), tuple(reference["split"]), reference["seed"],
                          reference["train_tosses"], reference["initial_twist"])  # fmt: skip
    train, table = setting.train, setting.table_height
    if not np.array_equal(train.toss_id, reference["train_toss_id"]):
        raise SystemExit(f"{args.fitted[0]} was fitted on other tosses than its split and seed give in {args.source}")
    starts = setting.starts(train)
    engine = load_engine(reference["engine"])
    for path, fit in zip(args.fitted, fits):
        m = score(engine, train, fit["parameters"], table, starts)
        print(json.dumps({"on": f"{args.fitted[0]} ({train.n} training tosses)", "parameters_of": path,
                          "objective": m["objective"], "position_error_pct": m.get("position_error_pct"),
                          "rotation_error_deg": m.get("rotation_error_deg"),
                          "own_objective": fit["train_metrics"]["objective"]}))  # fmt: skip


if __name__ == "__main__":
    main()
