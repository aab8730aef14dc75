"""A trained model's whole-toss errors with its frame integrated in more substeps (an experiment on the real tosses).

The models step once per camera frame (1/148 s): RK4 and then the contacts, at their time of impact. This script
scores a run's best checkpoint on a split's whole tosses (as ``evaluate`` does) with each frame split into K
substeps (``Simulator.substeps``), to measure what the frame-rate step itself costs in the metrics.

    python investigations/substeps.py runs/cubetoss-com/seed1 data/CubeToss --split val --substeps 1 2 4
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import time

import torch

from diffcontact.eval.tosses import predict_tosses, score_tosses
from diffcontact.run_dir import RunDir
from diffcontact.train.module import ContactLightningModule


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a training run of a measured-toss task")
    parser.add_argument("data", help="its imported dataset folder")
    parser.add_argument("--split", default="val")
    parser.add_argument("--substeps", type=int, nargs="+", default=[1, 2, 4])
    args = parser.parse_args()
    torch.set_num_threads(1)
    net = ContactLightningModule.from_checkpoint(RunDir(args.run).best_checkpoint()).net
    for k in args.substeps:
        net.simulator.substeps = k
        started = time.perf_counter()
        metrics = score_tosses(predict_tosses(net, args.data, args.split), args.data, args.split)
        print(json.dumps({"substeps": k, **metrics, "seconds": round(time.perf_counter() - started, 1)}), flush=True)


if __name__ == "__main__":
    main()
