"""Where a trained Rope model's 5-step error comes from, and whether its learned potential can carry the rope's forces.

    diffcontact generate Rope --out data
    diffcontact train Rope --out runs/Rope-mlp      # (with potential = "mlp" in a copy of the task file: the paper's)
    python investigations/rope_floor.py runs/Rope-mlp --data data

Prints, for the run's best model on the test trajectories:
- the 5-step error split into positions and velocities, and the velocity error of each node one frame ahead;
- the 5-step error from later frames of the same trajectories (the Fig. 3 error starts at frame 0);
- the frames the training chunks start at;
- the spread of the true acceleration of each node over the training chunks' states;
- a fresh network of the run's kind, fitted to the true forces directly (Adam, L1, ``--steps``): the error of the
  acceleration it reaches at each node.  A potential that cannot fit the forces when given them cannot learn them
  from trajectories.
Writes nothing.  Findings: docs/notes/2026-11-28-rope-error-floor.md.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
from pathlib import Path

import numpy as np
import torch

from diffcontact.eval.evaluate import load_run
from diffcontact.eval.metrics import relative_error, trajectory_error
from diffcontact.eval.rollouts import ground_truth, predict
from diffcontact.models.params import LinkedPotential, MLPPotential


def _row(name: str, values) -> str:
    return f"{name}: " + ", ".join(f"{v:.3g}" for v in values)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--data", default="data")
    ap.add_argument("--steps", type=int, default=3000, help="Adam steps of the direct fit to the forces")
    args = ap.parse_args()
    torch.set_num_threads(1)
    loaded = load_run(args.run, "Rope")
    task, net, folder = loaded.task, loaded.net.double(), Path(args.data) / "Rope"
    x, v, _, _ = ground_truth(folder, "test", None, task.config)
    x, v = x.double(), v.double()

    xh, vh = predict(net, x[:, 0], v[:, 0], 5)
    den = (x[:, :5].square().flatten(2).sum(-1) + v[:, :5].square().flatten(2).sum(-1)).sqrt()
    parts = [(a - b).square().flatten(2).sum(-1).sqrt() / den for a, b in ((xh, x[:, :5]), (vh, v[:, :5]))]
    print(_row("5-step error, positions and velocities alone", [p.sum(1).mean() for p in parts]))
    print(_row("velocity error one frame ahead by node (m/s)", (vh[:, 1] - v[:, 1]).norm(dim=-1).mean(0)))
    print("5-step error from frame s:")
    for s in (0, 1, 2, 5, 10, 20, 50):
        ph, pv = predict(net, x[:, s], v[:, s], 5)
        rel = relative_error(ph, pv, x[:, s : s + 5], v[:, s : s + 5])
        print(f"  s = {s}: {float(trajectory_error(rel, 5).mean()):.3e}")

    train = np.load(folder / "train.npz")
    starts = np.bincount(train["chunk_start"].astype(int))
    print(f"training chunks start at frames 0 … {len(starts) - 1}: " + " ".join(str(int(c)) for c in starts))
    states = torch.as_tensor(train["chunk_x"]).flatten(0, 1).double()
    xs = states.clone().requires_grad_(True)
    force = -torch.autograd.grad(task.params.potential_energy(xs).sum(), xs)[0]
    masses = task.params.inertia.masses.double()[None, :, None]
    print(_row("true acceleration over the chunks' states, standard deviation by node (m/s²)",
               (force / masses).norm(dim=-1).std(0)))  # fmt: skip

    kind = type(net.params.potential)
    gen = torch.Generator().manual_seed(0)
    n_inputs = states.shape[1] * states.shape[2]
    if kind is LinkedPotential:
        fresh = LinkedPotential(n_inputs, task.system.links, generator=gen)
    else:
        fresh = MLPPotential(n_inputs, generator=gen)
    fresh = fresh.double()
    opt = torch.optim.Adam(fresh.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.steps)
    pick = torch.Generator().manual_seed(1)
    for _ in range(args.steps):
        idx = torch.randint(0, states.shape[0], (256,), generator=pick)
        loss = (fresh.force(states[idx]) - force[idx]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        err = ((fresh.force(states) - force) / masses).norm(dim=-1).mean(0)
    print(
        _row(f"{kind.__name__} fitted to the true forces ({args.steps} steps): acceleration error by node (m/s²)", err)
    )


if __name__ == "__main__":
    main()
