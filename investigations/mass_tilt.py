"""How much the data say about the mass ratios: the training loss of the true model with tilted masses, beside
what a trained model still misses (docs/investigations.md, the Rope's masses).

    python investigations/mass_tilt.py Rope --run runs/matrix-final/Rope/CM-CD-CLNN/seed0

Masses are tilted linearly along the bodies, m_i·(1 + a·i/(n − 1)), for each tilt a; the loss (the training loss:
0.5·(mean |x̂ − x| + mean |v̂ − v|)) over the training chunks is evaluated with the exact simulator in float64 and
every other property true, once with gravity following the tilted masses (what a learned potential can do) and
once with gravity at the true masses.  With ``--run``, the trained model's loss on the same chunks, split into
chunks with and without a contact at the truth.
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


def with_masses(params, masses: torch.Tensor, gravity_follows: bool):
    """Params with ``masses``; the potential's gravity on them if ``gravity_follows`` (it reads the Params' masses),
    else on the original masses."""
    from diffcontact.state import Inertia

    pot = params.potential
    if not gravity_follows:
        pot = lambda x, _inertia: params.potential(x, params.inertia)  # noqa: E731
    return params.replace(inertia=Inertia(masses, params.inertia.moments), potential=pot)


def main() -> None:
    from diffcontact.data.store import load_split
    from diffcontact.simulator import simulator_for
    from diffcontact.state import State
    from diffcontact.systems import build_task

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("task", nargs="?", default="Rope")
    ap.add_argument("--data", default="data")
    ap.add_argument("--tilts", nargs="+", type=float, default=[0.003, 0.01, 0.03, 0.1])
    ap.add_argument("--run", type=Path, help="a trained run of the task: its loss on the same chunks")
    args = ap.parse_args()
    torch.set_num_threads(1)

    task = build_task(args.task)
    train = load_split(Path(args.data) / args.task, "train")
    x, v = train.chunk_x.to(torch.float64), train.chunk_v.to(torch.float64)
    sim = simulator_for(task)
    m0 = task.params.inertia.masses
    ramp = torch.arange(len(m0), dtype=m0.dtype) / max(len(m0) - 1, 1)
    print(f"{args.task}: {len(x)} training chunks; loss at the truth {chunk_loss(sim, task.params, x, v, task.dt):.3e}")
    for a in args.tilts:
        m = m0 * (1 + a * ramp)
        follows = chunk_loss(sim, with_masses(task.params, m, True), x, v, task.dt)
        fixed = chunk_loss(sim, with_masses(task.params, m, False), x, v, task.dt)
        print(f"tilt {a:.3f}: loss {follows:.3e} (gravity following the masses), {fixed:.3e} (gravity at the truth)")
    if args.run:
        from diffcontact.train.module import ContactLightningModule

        learned = json.loads((args.run / "learned.json").read_text())
        best = args.run / "checkpoints" / Path(learned["best_checkpoint"]).name
        module = ContactLightningModule.from_checkpoint(best)
        dtype = next(module.net.parameters()).dtype
        with torch.no_grad():
            _, _, hit = sim.rollout(State(x[:, 0], v[:, 0]), task.params, task.dt, x.shape[1])
            px, pv = module.net(x[:, 0].to(dtype), v[:, 0].to(dtype), x.shape[1])
        ex, ev = (px.double() - x).abs(), (pv.double() - v).abs()
        per = 0.5 * (ex.mean((1, 2, 3)) + ev.mean((1, 2, 3)))
        contact = hit[:, 1:].any(1)
        print(
            f"trained model {args.run}: loss {per.mean():.3e} (positions {0.5 * ex.mean():.3e}, velocities "
            f"{0.5 * ev.mean():.3e}); {int(contact.sum())} chunks with a contact {per[contact].mean():.3e}, "
            f"{int((~contact).sum())} without {per[~contact].mean():.3e}"
        )


if __name__ == "__main__":
    main()
