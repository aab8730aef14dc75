"""The 5-step error (Fig. 3) and the learned μ, e of a run's chosen checkpoint and of its last, on the test split.

    python investigations/checkpoint_error.py runs/noise/runs/CP3/CM-CD-CLNN/seed0 --data runs/noise/data

Where a run's checkpoint was chosen on its validation loss, this says what the last epoch would have given instead
(docs/training.md, "Noisy data": the runs that learn their chunks' first states now keep their last epoch).
Float64 rollouts of every test trajectory's first frames; the error
with its 95 % interval over the trajectories (as `diffcontact evaluate` gives it).
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
from pathlib import Path

import torch

from diffcontact.data.store import dataset_folder
from diffcontact.eval.loading import load_run
from diffcontact.eval.metrics import mean_interval, relative_error, trajectory_error
from diffcontact.eval.rollouts import rollout_split
from diffcontact.run_dir import RunDir


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--data", default=None, help="dataset root (default: the one each run was trained from)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for path in map(Path, args.runs):
        run = RunDir(path)
        for name, checkpoint in (("chosen", run.best_checkpoint()), ("last", run.last_checkpoint)):
            loaded = load_run(path, checkpoint=checkpoint)
            net = loaded.net.double()
            root = args.data or loaded.config["args"].get("data_root", "data")
            with torch.no_grad():
                ro = rollout_split(net, dataset_folder(root, loaded.task_name), "test", 5, loaded.task.config)
            mean, half = mean_interval(trajectory_error(relative_error(ro.x_hat, ro.v_hat, ro.x, ro.v), 5))
            mu, e = (float(t.detach().mean()) for t in (net.params.mu, net.params.e))
            print(
                f"{path} {name} ({checkpoint.name}): 5-step error {mean:.4g} ± {half:.2g}, "
                f"μ {mu:.4f}, e {e:.4f} (means over the slots)"
            )


if __name__ == "__main__":
    main()
