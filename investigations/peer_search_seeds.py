"""How far a peer's fit depends on its search: the same training tosses fitted with several seeds of the search.

``diffcontact peers fit`` ties the seed of its search to the seed of the split (and so to the training tosses).
This keeps the split and the first N training tosses of seed 0, as the toss sweep's cell at N does, and changes the
seed of the search alone (CMA-ES's samples and the restarts' random starts). For each seed it prints, as a JSON
line, the best training objective, the test metrics, the fitted parameters and, with ``--reference``, the paired
difference of the reference's per-toss position error minus the fit's (``pose_metrics.paired_difference``) on the
same test tosses; the reference is an exact model's test predictions.npz at the same N (``diffcontact evaluate``,
or a sweep cell's eval/).

    python investigations/peer_search_seeds.py bullet contactnets_cube_tosses.npz -n 16 --seeds 0 1 2 3 \
        --reference runs/sweep-com/runs/N16/CM-CD-CLNN/eval/predictions.npz
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json

import numpy as np

from diffcontact.data.tosses import read_tosses
from diffcontact.eval.pose_metrics import paired_difference, per_toss_position_error
from diffcontact.peers import load_engine
from diffcontact.peers.cube import COM_PARAMETERS, HALF_EXTENT
from diffcontact.peers.fit import DEFAULT_BUDGET, fit_parameters, peer_tosses, rollout_metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("engine", help="mujoco or bullet")
    parser.add_argument("source", help="the tosses (a ContactNets .npz or folder of K.pt)")
    parser.add_argument("-n", type=int, required=True, help="training tosses, the sweep's first N of split seed 0")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="seeds of the search")
    parser.add_argument("--budget", type=int, default=DEFAULT_BUDGET, help="evaluations of each search")
    parser.add_argument("--jobs", type=int, default=1, help="processes scoring each search's candidates")
    parser.add_argument("--reference", help="an exact model's test predictions.npz at the same N")
    args = parser.parse_args()
    engine = load_engine(args.engine)
    setting = peer_tosses(read_tosses(args.source), train_tosses=args.n)  # (the sweep's split, seed 0)
    train, test, table = setting.train, setting.part("test"), setting.table_height
    train_starts, test_starts = setting.starts(train), setting.starts(test)
    reference = None
    if args.reference:
        with np.load(args.reference) as z:
            if not np.array_equal(z["toss_id"], test.toss_id):
                raise SystemExit(f"{args.reference} holds other test tosses than split seed 0's")
            reference = per_toss_position_error(z["position"], test.position, test.offsets, [HALF_EXTENT] * 3)
    space = engine.PARAMETERS + COM_PARAMETERS
    for seed in args.seeds:
        fit = fit_parameters(engine, train, table, args.budget, seed, lambda s: None, train_starts, space, args.jobs)
        position, quaternion = engine.simulate(test_starts, fit["params"], table)
        line = {"engine": args.engine, "n": args.n, "search_seed": seed, "budget": args.budget,
                "train_objective": fit["train_metrics"]["objective"],
                "runs": [(r["popsize"], r["best"]) for r in fit["optimiser"]["runs"]],
                "test": rollout_metrics(test, position, quaternion, table), "params": fit["params"]}  # fmt: skip
        if reference is not None:
            errors = per_toss_position_error(position, test.position, test.offsets, [HALF_EXTENT] * 3)
            line["reference_minus_fit"] = paired_difference(reference, errors)
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
