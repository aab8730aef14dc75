"""Why a trained run's test trajectories are outliers: which contact slots they collide on, and the training loss
as a function of one slot's μ (docs/investigations.md, "BP5's and BD5's outliers").

    python investigations/slot_profile.py runs/BP5 --slot 29      # after diffcontact train BP5 and evaluate

Prints the test trajectories with the largest 5-step errors (from RUN/eval/metrics.json) and the slots each collides
on in frames 1-4 (replayed with the true parameters), then the L1 loss over the training chunks that hold a
collision of ``--slot``, with every property as learned except that slot's μ, scanned over ``--mus`` (float64).
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from loss_landscape import chunk_loss  # noqa: E402


def slots_hit(task, sim, x: torch.Tensor, v: torch.Tensor) -> list[set[int]]:
    """The contact slots each trajectory collides on between its frames: x, v (N, T, P, d) -> N sets."""
    hit: list[set[int]] = [set() for _ in range(len(x))]
    with torch.no_grad():
        for t in range(1, x.shape[1]):
            x1, _ = sim.flow(task.params, x[:, t - 1], v[:, t - 1], task.dt)
            c = task.system.detector.detect(x1)
            if c is not None:
                for b, act, slot in zip(c.index.tolist(), c.active, c.slot):
                    hit[b] |= set(slot[act].tolist())
    return hit


def main() -> None:
    from diffcontact.data.store import load_split
    from diffcontact.eval.loading import load_run

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--slot", type=int, required=True)
    ap.add_argument("--data", default="data")
    ap.add_argument("--top", type=int, default=8, help="outlier trajectories listed")
    ap.add_argument("--mus", type=float, nargs="+", default=[0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 1.0, 1.5, 2.0, 3.0])
    args = ap.parse_args()
    torch.set_num_threads(1)

    loaded = load_run(args.run)
    net, task = loaded.net.double(), loaded.task
    sim = net.simulator
    folder = Path(args.data) / loaded.task_name
    metrics_path = Path(args.run) / "eval" / "metrics.json"
    if metrics_path.is_file():
        errors = torch.tensor(json.loads(metrics_path.read_text())["trajectory_error"]["per_trajectory"])
        test = load_split(folder, "test")
        hit = slots_hit(task, sim, test.x[:, :5], test.v[:, :5])
        print("largest 5-step errors: trajectory, error, slots collided on in frames 1-4")
        for i in errors.argsort(descending=True)[: args.top].tolist():
            print(f"  {i:4d}  {errors[i]:.3g}  {sorted(hit[i])}")
    train = load_split(folder, "train")
    hit = slots_hit(task, sim, train.chunk_x, train.chunk_v)
    keep = torch.tensor([args.slot in h for h in hit])
    with torch.no_grad():
        params = net.params()
    learned, true = params.mu[args.slot].item(), task.params.mu[args.slot].item()
    n = int(keep.sum())
    print(f"slot {args.slot}: μ learned {learned:.4g}, true {true:.4g}; {n} training chunks collide on it")
    for mu in sorted({*args.mus, learned, true}):
        mus = params.mu.clone()
        mus[args.slot] = mu
        loss = chunk_loss(sim, params.replace(mu=mus), train.chunk_x[keep], train.chunk_v[keep], task.dt)
        print(f"  μ = {mu:.4g}: loss {loss:.4e}")


if __name__ == "__main__":
    main()
