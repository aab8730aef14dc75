"""Is an MLP-CD-CLNN run's velocity jump a function of the state, or a constant?

    python investigations/jump_alive.py runs/efficiency/N25/runs/Rope200/MLP-CD-CLNN/seed0 \
        runs/efficiency-n400/N400/runs/Rope200/MLP-CD-CLNN/seed0 --data runs/efficiency/N25/data

For each run (its best checkpoint) on the first frames of the test trajectories: the share of each hidden layer's
ReLU units alive on at least one state, the jump's spread over the states (0: the MLP outputs its last bias, the
same Δv everywhere) and its mean size, and the 5-step error of Fig. 3 on ``--n`` test trajectories with the jump as
learned and with it set to zero.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse

import torch

from diffcontact.data.store import dataset_folder
from diffcontact.eval.loading import load_run
from diffcontact.eval.metrics import relative_error, trajectory_error
from diffcontact.eval.rollouts import ground_truth, predict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--data", default=None, help="dataset root (default: the one each run was trained from)")
    parser.add_argument("--n", type=int, default=40, help="test trajectories rolled out")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for path in args.runs:
        loaded = load_run(path)
        net = loaded.net.double()
        if not hasattr(net, "jump"):
            raise SystemExit(f"{path}: {loaded.model_name} has no velocity jump (MLP-CD-CLNN has)")
        root = args.data or loaded.config["args"].get("data_root", "data")
        x, v, _, _ = ground_truth(dataset_folder(root, loaded.task_name), "test", 5, loaded.task.config)
        x, v = x[: args.n], v[: args.n]
        h, alive = torch.cat([x[:, :4].flatten(2), v[:, :4].flatten(2)], -1).flatten(0, 1), []
        with torch.no_grad():
            for layer in net.jump:
                h = layer(h)
                if isinstance(layer, torch.nn.ReLU):
                    alive.append(float((h > 0).any(0).double().mean()))
        xh, vh = predict(net, x[:, 0], v[:, 0], 5)
        learned = float(trajectory_error(relative_error(xh, vh, x, v), 5).mean())
        with torch.no_grad():
            net.jump[-1].weight.zero_()
            net.jump[-1].bias.zero_()
        xz, vz = predict(net, x[:, 0], v[:, 0], 5)
        zeroed = float(trajectory_error(relative_error(xz, vz, x, v), 5).mean())
        print(
            f"{path}: alive units per hidden layer {[round(a, 3) for a in alive]}; jump spread over states "
            f"{float(h.std(0).mean()):.3g} m/s, mean |Δv| {float(h.abs().mean()):.6g} m/s; 5-step error "
            f"{learned:.5g} as learned, {zeroed:.5g} with the jump zeroed ({len(x)} test trajectories)"
        )


if __name__ == "__main__":
    main()
