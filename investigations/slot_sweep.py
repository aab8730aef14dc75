"""The full-batch training loss and its gradient as one slot's μ or e of a trained run is set to given values.

    python investigations/slot_sweep.py runs/superseded/BD5-CM-CD-CLNN-mu-sixth/seed0 4 0.5,0.77,1.0,1.2,1.4,1.6

Loads the run's best checkpoint and its training chunks (in the run's dtype), sets the coefficient of ``slot`` to
each value (every other parameter as learned) and prints the loss over all training chunks and its derivative
with respect to that coefficient.  Shows where the minimum lies and how steep the way to it is (docs/investigations.md:
why BD5's high-friction slots stopped short).
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
from pathlib import Path

import torch


def main() -> None:
    from diffcontact.data.store import load_split
    from diffcontact.train.module import ContactLightningModule

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("slot", type=int)
    ap.add_argument("values", help="comma-separated values of the coefficient")
    ap.add_argument("--coef", choices=("mu", "e"), default="mu")
    args = ap.parse_args()
    torch.set_num_threads(1)

    learned = json.loads((args.run / "learned.json").read_text())
    config = json.loads((args.run / "config.json").read_text())["args"]
    module = ContactLightningModule.from_checkpoint(args.run / "checkpoints" / Path(learned["best_checkpoint"]).name)
    if config.get(f"{args.coef}_transform") != "projected":
        raise SystemExit(f"{args.run}: {args.coef} is not projected (its parameter is not its value)")
    dtype = getattr(torch, config.get("dtype", "float32"))
    train = load_split(Path(config["data_root"]) / config["task"], "train")
    x, v = train.chunk_x.to(dtype), train.chunk_v.to(dtype)
    raw = getattr(module.net.params, f"{args.coef}_raw")
    print(f"{args.coef}[{args.slot}]: learned {raw.detach()[args.slot].item():.4f}")
    for value in (float(s) for s in args.values.split(",")):
        with torch.no_grad():
            raw[args.slot] = value
        raw.grad = None
        loss = module.loss((x, v))
        loss.backward()
        print(f"{value:.3f}  loss {loss.item():.4e}  dloss/d{args.coef} {raw.grad[args.slot].item():+.3e}", flush=True)


if __name__ == "__main__":
    main()
