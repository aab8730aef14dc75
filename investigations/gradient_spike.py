"""Which chunk of a spiking training step makes its gradient, and through what.

    python investigations/train_trace.py Rope --data DATA --out RUN      # writes RUN/spike-*.pt
    python investigations/gradient_spike.py RUN/spike-epoch2-step36.pt --run RUN

Loads the module as it entered the step and the step's batch, and gives each chunk's loss and the norm of its
gradient (the batch's loss is the mean of the chunks'), largest first, as trained (float32) and in float64.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse

import torch

from diffcontact.run_dir import RunDir
from diffcontact.systems.registry import build_task
from diffcontact.train.module import ContactLightningModule, saved_config


def spiking_module(spike: dict, run: RunDir) -> ContactLightningModule:
    """The module of ``run`` with the state it had as it entered the spiking step."""
    config = saved_config(torch.load(run.last_checkpoint, map_location="cpu", weights_only=True))
    module = ContactLightningModule(config, built_task=build_task(config.task))
    module.load_state_dict(spike["state_dict"])
    return module.train()


def chunk_gradients(module: ContactLightningModule, batch: list) -> tuple[torch.Tensor, torch.Tensor]:
    """Each chunk's loss (B,) and the norm of its loss's gradient in the parameters (B,)."""
    losses, norms = [], []
    for i in range(len(batch[0])):
        one = [t[i : i + 1] for t in batch]
        first = module._first(one, "train")
        module.zero_grad()
        loss, _ = module._losses(one, None, first)
        loss.backward()
        norms.append(torch.sqrt(sum(p.grad.double().square().sum() for p in module.parameters() if p.grad is not None)))
        losses.append(loss.detach())
    return torch.stack(losses), torch.stack(norms)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("spike")
    parser.add_argument("--run", required=True)
    parser.add_argument("--top", type=int, default=8)
    args = parser.parse_args()
    torch.set_num_threads(1)
    spike = torch.load(args.spike, map_location="cpu", weights_only=False)
    module = spiking_module(spike, RunDir(args.run))
    batch = spike["batch"]
    losses, norms = chunk_gradients(module, batch)
    print(f"step's gradient norm {spike['norm']:.4g} (median of the steps before {spike['median']:.3g}); "
          f"chunks' norms: median {float(norms.median()):.3g}, mean {float(norms.mean()):.3g}")  # fmt: skip
    top = norms.argsort(descending=True)[: args.top]
    wide = [t[top].double() if t.is_floating_point() else t[top] for t in batch]
    losses64, norms64 = chunk_gradients(module.double(), wide)
    for j, i in enumerate(top.tolist()):
        print(f"  chunk {int(batch[4][i])}: loss {float(losses[i]):.4f} (float64 {float(losses64[j]):.4f}), "
              f"gradient norm {float(norms[i]):.4g} (float64 {float(norms64[j]):.4g})")  # fmt: skip


if __name__ == "__main__":
    main()
