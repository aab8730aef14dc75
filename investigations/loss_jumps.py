"""Why a run that learns its chunks' first states has its training loss rise late in training: where the rise is,
and whether it is smooth or made of jumps.

    python investigations/loss_jumps.py runs/noise-0.05/runs/CP3-e/CM-CD-CLNN/seed0 --data runs/noise-0.05/data \
        --early checkpoints/best-epoch=34.ckpt

Two checkpoints of one run (``--early``, a path relative to the run unless absolute, and its last) are set side by
side on the training chunks:
1. each checkpoint's training loss per chunk, its first-state corrections first fitted again under its own model
   (``--refit`` trial steps at the full step, the training's rule), split into the chunks with and without a collision,
   and how much of the rise the chunks that rose most make;
2. the same with the two checkpoints' e swapped (is it e, or the rest of the model?);
3. along the straight line between the two (parameters and corrections, ``--points`` points), the largest change of
   a chunk's loss between neighbouring points, for the chunks that rose most and those that fell most: a jump is one
   step of the size of the whole change, a smooth change is spread over the line.
With ``--e E ...`` it answers another question instead: where the training loss of the last checkpoint, least over
its first states (fitted again ``--refit`` trial steps at each value), is least in e (docs/training.md, "Noisy data":
μ and e at the full rate).
float32, as trained; one thread.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
from pathlib import Path

import torch

from diffcontact.run_dir import RunDir
from diffcontact.train.datamodule import ContactDataModule
from diffcontact.train.first_states import FirstStates
from diffcontact.train.module import ContactLightningModule

BATCH = 50


def chunk_losses(module: ContactLightningModule, chunks, dx: torch.Tensor, dv: torch.Tensor) -> torch.Tensor:
    """Each training chunk's loss (n,) under ``module`` with first-state corrections ``dx``, ``dv``."""
    out = []
    with torch.no_grad():
        for s in range(0, len(chunks), BATCH):
            idx = torch.arange(s, min(len(chunks), s + BATCH))
            out.append(module._losses(_batch(chunks, idx), None, (dx[idx], dv[idx]))[1])
    return torch.cat(out)


def _batch(chunks, idx: torch.Tensor) -> list:
    return [chunks.x[idx], chunks.v[idx], chunks.t, chunks.collision[idx], idx]


def refit(module: ContactLightningModule, chunks, steps: int) -> FirstStates:
    """The module's training corrections, moved ``steps`` more trial steps at the full step under its model."""
    stored = module.first_train
    states = FirstStates(len(chunks), tuple(stored.dx.shape[1:]), stored.dx.dtype, stored.coords)
    states.dx.copy_(stored.dx)
    states.dv.copy_(stored.dv)
    for _ in range(steps):
        for s in range(0, len(chunks), BATCH):
            idx = torch.arange(s, min(len(chunks), s + BATCH))
            batch = _batch(chunks, idx)
            dx, dv = states.take(idx)
            loss, each = module._losses(batch, None, (dx, dv))
            grads = torch.autograd.grad(loss, (dx, dv))
            with torch.no_grad():
                states.update(
                    idx, *grads, module.config.first_state_lr, each, lambda a, b: module._losses(batch, None, (a, b))[1]
                )
    return states


def split(losses: torch.Tensor, collision: torch.Tensor) -> str:
    hit, free = losses[collision].mean(), losses[~collision].mean()
    return f"all {losses.mean():.5f}, with a collision {hit:.5f}, free {free:.5f}"


def scan_e(run: RunDir, data: str, values: list[float], steps: int) -> None:
    """The training loss of the run's last checkpoint at each e of ``values``, its corrections fitted again."""
    module = ContactLightningModule.from_checkpoint(run.last_checkpoint)
    module.train()
    chunks = ContactDataModule(module.config.task, data, dtype=getattr(torch, module.config.dtype))._dataset("train")
    collision = chunks.collision.bool()
    for e in values:
        with torch.no_grad():
            module._params.e_raw.fill_(e)
        states = refit(module, chunks, steps)
        print(f"e {e}: {split(chunk_losses(module, chunks, states.dx, states.dv), collision)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run")
    parser.add_argument("--data", required=True, help="the dataset root the run was trained on")
    parser.add_argument("--early", help="the earlier checkpoint (relative to the run, or absolute)")
    parser.add_argument("--e", nargs="+", type=float, help="instead: the last checkpoint's loss at each of these e")
    parser.add_argument("--refit", type=int, default=12, help="trial steps of the corrections before scoring")
    parser.add_argument("--points", type=int, default=41, help="points on the line between the two checkpoints")
    parser.add_argument("--top", type=int, default=8, help="chunks shown that rose most (and half as many that fell)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    run = RunDir(Path(args.run))
    if args.e:
        return scan_e(run, args.data, args.e, args.refit)
    if not args.early:
        raise SystemExit("give --early CHECKPOINT (or --e VALUES)")
    early_path = Path(args.early) if Path(args.early).is_absolute() else run.path / args.early
    early = ContactLightningModule.from_checkpoint(early_path)
    last = ContactLightningModule.from_checkpoint(run.last_checkpoint)
    if not early.first_states:
        raise SystemExit(f"{args.run}: the run does not learn its chunks' first states")
    chunks = ContactDataModule(early.config.task, args.data, dtype=getattr(torch, early.config.dtype))._dataset("train")
    collision = chunks.collision.bool()
    for m in (early, last):
        m.train()  # (the training's loss, as the run logged it)

    def score(m: ContactLightningModule) -> torch.Tensor:
        states = refit(m, chunks, args.refit)
        return chunk_losses(m, chunks, states.dx, states.dv)

    e_early, e_last = float(early._params.e.detach().mean()), float(last._params.e.detach().mean())
    a, b = score(early), score(last)
    print(f"{early_path.name} (e {e_early:.4f}): {split(a, collision)}")
    print(f"{run.last_checkpoint.name} (e {e_last:.4f}): {split(b, collision)}")
    rise = (b - a)[collision]
    order = rise.sort(descending=True).values
    total = float(rise.sum())
    for share in (0.02, 0.05, 0.1):
        k = max(1, int(share * len(rise)))
        print(
            f"  the {k} chunks with a collision that rose most ({share:.0%}): "
            f"{float(order[:k].sum()) / total:.0%} of their rise"
        )
    print(
        f"  with a collision: {int((rise > 0).sum())} rose, {int((rise < 0).sum())} fell; "
        f"median change {rise.median():+.5f}"
    )

    with torch.no_grad():
        raw = early._params.e_raw.clone()
        early._params.e_raw.copy_(last._params.e_raw)
    print(f"early model with the last e: {split(score(early), collision)}")
    with torch.no_grad():
        early._params.e_raw.copy_(raw)

    # the straight line between the two, parameters and stored corrections together
    change = b - a
    idx = torch.cat([change.argsort(descending=True)[: args.top], change.argsort()[: max(1, args.top // 2)]])
    line = ContactLightningModule.from_checkpoint(run.last_checkpoint)
    line.train()
    pa, pb = dict(early.net.named_parameters()), dict(last.net.named_parameters())
    fa, fb = early.first_train, last.first_train
    ts = torch.linspace(0, 1, args.points)
    rows = []
    with torch.no_grad():
        for t in ts:
            for k, p in line.net.named_parameters():
                p.copy_(pa[k] + t * (pb[k] - pa[k]))
            dx, dv = fa.dx[idx] + t * (fb.dx[idx] - fa.dx[idx]), fa.dv[idx] + t * (fb.dv[idx] - fa.dv[idx])
            rows.append(line._losses(_batch(chunks, idx), None, (dx, dv))[1])
    path = torch.stack(rows)
    print("along the line (stored corrections): chunk, loss at the two ends, its largest step between neighbours")
    for j, i in enumerate(idx.tolist()):
        steps = path[:, j].diff().abs()
        print(
            f"  {i:5d} ({'collision' if collision[i] else 'free'}): {path[0, j]:.3f} -> {path[-1, j]:.3f}, "
            f"largest step {steps.max():.3f} at t {ts[int(steps.argmax()) + 1]:.3f}, total |steps| {steps.sum():.3f}"
        )


if __name__ == "__main__":
    main()
