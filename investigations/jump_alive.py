"""Is a baseline's velocity jump a function of the state, or a constant (or nothing)?

    python investigations/jump_alive.py runs/efficiency/N25/runs/Rope200/MLP-CD-CLNN/seed0 \
        runs/efficiency-n400/N400/runs/Rope200/MLP-CD-CLNN/seed0 --data runs/efficiency/N25/data

For each run (its best checkpoint) of MLP-CD-CLNN (the jump: its MLP) or IN-CP-CLNN (the jump: the interaction
network's output, added to the learned flow's velocity), over the steps from the first four frames of ``--n`` test
trajectories: the share of each hidden layer's ReLU units alive on at least one state, the jump's spread over the
states (0: the network outputs its last bias, the same Δv everywhere), its mean size and its mean on the first
point (a constant jump's value), and the 5-step error of
Fig. 3 on those trajectories with the jump as learned and with it set to zero (the last layer's weights and bias).
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
from diffcontact.models.baselines.interaction import InteractionNetCLNN


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
        networks, jump = _jump_networks(net, path, loaded.model_name)
        root = args.data or loaded.config["args"].get("data_root", "data")
        x, v, _, _ = ground_truth(dataset_folder(root, loaded.task_name), "test", 5, loaded.task.config)
        x, v = x[: args.n], v[: args.n]
        relus = [m for network in networks for m in network if isinstance(m, torch.nn.ReLU)]
        alive: list[torch.Tensor] = [torch.zeros(0)] * len(relus)
        out: list[torch.Tensor] = []

        def unit_alive(i: int):
            def hook(_module, _inputs, h):  # (a unit is alive where it is positive on some state)
                alive[i] = (h > 0).flatten(0, -2).any(0)

            return hook

        hooks = [m.register_forward_hook(unit_alive(i)) for i, m in enumerate(relus)]
        hooks.append(jump.register_forward_hook(lambda _m, _i, h: out.append(h.flatten(1))))
        with torch.no_grad():
            net.step(x[:, :4].flatten(0, 1), v[:, :4].flatten(0, 1))
        for h in hooks:
            h.remove()
        dv = out[0]
        xh, vh = predict(net, x[:, 0], v[:, 0], 5)
        learned = float(trajectory_error(relative_error(xh, vh, x, v), 5).mean())
        with torch.no_grad():
            jump[-1].weight.zero_()
            jump[-1].bias.zero_()
        xz, vz = predict(net, x[:, 0], v[:, 0], 5)
        zeroed = float(trajectory_error(relative_error(xz, vz, x, v), 5).mean())
        print(
            f"{path}: alive units per hidden layer {[round(float(a.double().mean()), 3) for a in alive]}; jump "
            f"spread over states {float(dv.std(0).mean()):.3g} m/s, mean |Δv| {float(dv.abs().mean()):.6g} m/s, "
            f"mean Δv of the first point {[float(f'{c:.3g}') for c in dv.mean(0)[: x.shape[-1]]]} m/s; "
            f"5-step error {learned:.5g} as learned, {zeroed:.5g} with the jump zeroed ({len(x)} test trajectories)"
        )


def _jump_networks(net, path: str, model: str) -> tuple[list[torch.nn.Sequential], torch.nn.Sequential]:
    """The networks whose ReLU units make a baseline's velocity jump, and the one whose output is the jump."""
    if hasattr(net, "jump"):  # (MLP-CD-CLNN)
        return [net.jump], net.jump
    if isinstance(net, InteractionNetCLNN):
        return [net.net.relational, net.net.object], net.net.object
    raise SystemExit(f"{path}: {model} has no velocity jump apart from a learned flow (MLP-CD-CLNN and IN-CP-CLNN do)")


if __name__ == "__main__":
    main()
