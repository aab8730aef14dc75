"""A trained run's whole-toss errors with its μ alone changed: each value of ``--mu`` (absolute) or ``--offset``
(added to the run's μ), the rest of the model as trained, scored on a split's whole tosses as ``evaluate`` scores
them. What ``train/calibrate.py`` searches, laid out on a grid (docs/real_data.md, "How far μ sets the slide").

    python investigations/run_mu_scan.py runs/cubetoss-com/seed0 data/CubeToss --split train --mu 0.166 0.170 0.174
    python investigations/run_mu_scan.py runs/cubetoss-com/seed1 data/CubeToss --split val --offset -0.004 0 0.004
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import time

import torch

from diffcontact.eval.loading import load_run
from diffcontact.eval.tosses import predict_tosses, score_tosses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a trained run of a measured dataset")
    parser.add_argument("data", help="its imported dataset folder")
    parser.add_argument("--split", default="val")
    values = parser.add_mutually_exclusive_group(required=True)
    values.add_argument("--mu", type=float, nargs="+", help="values of μ")
    values.add_argument("--offset", type=float, nargs="+", help="values added to the run's μ")
    args = parser.parse_args()
    torch.set_num_threads(1)
    net = load_run(args.run).net
    mu_raw = net.params.mu_raw  # (the projected μ: μ itself)
    trained = mu_raw.detach().clone()
    rows = []
    for mu in args.mu or [float(trained[0]) + o for o in args.offset]:
        started = time.perf_counter()
        with torch.no_grad():
            mu_raw.fill_(mu)
        m = score_tosses(predict_tosses(net, args.data, args.split), args.data, args.split)
        rows.append({"mu": mu, "seconds": time.perf_counter() - started} | m)
        position, rotation = m["position_error_pct"], m["rotation_error_deg"]
        print(f"μ {mu:.4f}: position {position:.2f} %, rotation {rotation:.2f}°", flush=True)
    print(json.dumps({"run": args.run, "split": args.split, "trained_mu": trained.tolist(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
