"""Which validation figure follows the test error across one run's checkpoints?

    python investigations/train_trace.py Rope --data DATA --out RUN --every 5     # checkpoints every 5 epochs
    python investigations/checkpoint_criteria.py RUN --data DATA [--step 10]

For every checkpoint in RUN/checkpoints/trace (and the run's chosen and last ones) one row: the 5-step error on the
clean test split (what `diffcontact evaluate` reports; float64 rollouts from the test trajectories' first frames),
and three losses the run could have chosen its checkpoint by, on the noisy validation chunks: the run's own val/loss
(each chunk from its first frame as corrected by the learned first states, as they stood at that checkpoint), the
loss from the recorded first frames, and on the training chunks with their corrections.  A run that learns its
chunks' first states chooses its checkpoint by the first (docs/training.md, "Noisy data").
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
import re
from pathlib import Path

import torch

from diffcontact.data.store import dataset_folder
from diffcontact.eval.metrics import mean_interval, relative_error, trajectory_error
from diffcontact.eval.rollouts import rollout_split
from diffcontact.run_dir import RunDir
from diffcontact.systems.registry import build_task
from diffcontact.train.module import ContactLightningModule
from diffcontact.train.run import _data


def _epoch(path: Path) -> int:
    found = re.search(r"epoch=(\d+)", path.name)
    return int(found.group(1)) if found else 10**9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run")
    parser.add_argument("--data", required=True)
    parser.add_argument("--step", type=int, default=1, help="every this many of the traced checkpoints")
    args = parser.parse_args()
    torch.set_num_threads(1)
    run = RunDir(args.run)
    traced = sorted((run.path / "checkpoints" / "trace").glob("*.ckpt"), key=_epoch)[:: args.step]
    paths = traced + [run.best_checkpoint(), run.last_checkpoint]
    first = ContactLightningModule.from_checkpoint(paths[0])
    data = _data(first.config)
    data.setup()
    val, train = data.splits["val"], data.splits["train"]
    folder = dataset_folder(args.data, first.task.config.name)
    print("| checkpoint | test 5-step error | val/loss (corrected) | val, recorded first frames | train (corrected) |")
    print("| --- | --- | --- | --- | --- |")
    for path in paths:
        module = ContactLightningModule.from_checkpoint(path, build_task(first.config.task)).eval()
        with torch.no_grad():
            corrected = float(module.loss(module.as_fitted("val", val.chunk_x, val.chunk_v)))
            recorded = float(module.loss((val.chunk_x, val.chunk_v)))
            fitted = float(module.loss(module.as_fitted("train", train.chunk_x, train.chunk_v)))
            net = module.net.double()
            ro = rollout_split(net, folder, "test", 5, module.task.config)
            mean, half = mean_interval(trajectory_error(relative_error(ro.x_hat, ro.v_hat, ro.x, ro.v), 5))
        print(f"| {path.name} | {mean:.4g} ± {half:.2g} | {corrected:.4f} | {recorded:.4f} | {fitted:.4f} |",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
