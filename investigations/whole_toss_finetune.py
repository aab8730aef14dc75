"""Fine-tune a trained CubeToss model on whole tosses (an experiment on the real cube tosses).

Training cuts each training toss into windows of 80 frames, 80 apart: a toss of 101 frames (the median) gives one
window, its frames 0-79, and its last frames, where the cube slides to rest and the whole-toss error is largest,
are never in the loss. This script takes a run's best checkpoint and goes on training its parameters with a loss
over every frame of every whole training toss (rolled out from its first state, as ``evaluate`` does; the same
L1 loss of positions, axis points weighed by ``axis_scale``, averaged per toss), and scores the validation tosses'
position error after each epoch.

    python investigations/whole_toss_finetune.py runs/cubetoss-com/seed0 data/CubeToss --epochs 6 --out ft.json
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from diffcontact.data.measured import tosses_to_points
from diffcontact.eval.tosses import predict_tosses, recorded_tosses, score_tosses
from diffcontact.run_dir import RunDir
from diffcontact.train.module import ContactLightningModule


def batches_by_length(lengths: np.ndarray, size: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Toss indices in batches of about ``size`` of similar length (little padding), in a random order."""
    order = np.argsort(lengths + rng.uniform(0, 1, len(lengths)))
    groups = np.array_split(order, max(1, round(len(order) / size)))
    return [groups[i] for i in rng.permutation(len(groups))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("data")
    parser.add_argument("--epochs", type=int, default=6)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)

    module = ContactLightningModule.from_checkpoint(RunDir(Path(args.run)).best_checkpoint())
    net, dtype = module.net, torch.float32
    scale = module._point_scale[:, None]
    tosses, request = recorded_tosses(args.data, "train")
    x, v = tosses_to_points(tosses, request["table_height_m"], request["half_extents_m"])
    x, v = torch.from_numpy(x), torch.from_numpy(v)
    starts, lengths = tosses.offsets[:-1], tosses.lengths
    rng = np.random.default_rng(args.seed)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    history = []

    def record(epoch: int, train_loss: float | None, seconds: float) -> None:
        metrics = score_tosses(predict_tosses(net, args.data, "val"), args.data, "val")
        net.to(dtype)
        p = module.learned
        row = {
            "epoch": epoch,
            "train_loss": train_loss,
            "val_position_pct": metrics["position_error_pct"],
            "val_rotation_deg": metrics["rotation_error_deg"],
            "mu": p.mu.tolist() if p is not None else None,
            "e": p.e.tolist() if p is not None else None,
            "params": {n: t.detach().tolist() for n, t in net.named_parameters()},
            "seconds": round(seconds, 1),
        }
        history.append(row)
        print(json.dumps({k: row[k] for k in ("epoch", "train_loss", "val_position_pct", "mu", "e", "seconds")}),
              flush=True)  # fmt: skip
        Path(args.out).write_text(json.dumps({"args": vars(args), "history": history}, indent=1))

    net.to(dtype)
    record(0, None, 0.0)
    for epoch in range(1, args.epochs + 1):
        started, losses = time.perf_counter(), []
        for idx in batches_by_length(lengths, args.batch, rng):
            T = int(lengths[idx].max())
            rows = np.minimum(starts[idx][:, None] + np.arange(T)[None], (starts[idx] + lengths[idx] - 1)[:, None])
            xb, vb = x[rows].to(dtype), v[rows].to(dtype)
            keep = torch.from_numpy(np.arange(T)[None] < lengths[idx][:, None]).to(dtype)  # (B, T)
            px, _ = net(xb[:, 0], vb[:, 0], T)
            err = (scale.to(dtype) * (px - xb)).abs().flatten(2).mean(2)  # (B, T)
            loss = ((err * keep).sum(1) / keep.sum(1)).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            module.learned.project_()
            losses.append(loss.item())
        record(epoch, float(np.mean(losses)), time.perf_counter() - started)


if __name__ == "__main__":
    main()
