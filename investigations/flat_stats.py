"""How often training meets flat directions (solver/least_norm.py), and how large q's flat part is there.

python investigations/flat_stats.py RUN_DIR [--data data]: replays one epoch of the run's training batches through
the model of its best checkpoint (and through the initial model of the same seed), and prints per phase the number
of contact problems, those with flat directions, how many had q's flat part at rounding level (minimum-norm
minimiser) and how many of those had more than one minimiser, the largest relative flat part of q among them, and
the solver statuses, and how many flat problems have q's flat part ‖Π_N q‖/‖q‖ below 1e-6 … 1e-1.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
from pathlib import Path

import torch

from diffcontact.solver import Status, least_norm
from diffcontact.train.datamodule import ContactDataModule
from diffcontact.train.module import ContactLightningModule


def replay(module: ContactLightningModule, data: ContactDataModule) -> dict:
    stats = {"problems": 0, "flat": 0, "consistent": 0, "ratio_max_consistent": 0.0, "ratio_min_other": None}
    ratios = []
    analyse = least_norm._analyse

    def recording(A, q, used, tol, mu=None):
        out = analyse(A, q, used, tol, mu)
        ratio, c = out["part"], out["consistent"]  # (q's flat part relative to q, and whether it was dropped)
        stats["flat"] += len(c)
        stats["consistent"] += int(c.sum())
        stats["enters_cones"] = stats.get("enters_cones", 0) + int(out["enters"].sum())
        ratios.append(ratio)
        if c.any():
            stats["ratio_max_consistent"] = max(stats["ratio_max_consistent"], float(ratio[c].max()))
        if (~c).any():
            low = float(ratio[~c].min())
            stats["ratio_min_other"] = low if stats["ratio_min_other"] is None else min(stats["ratio_min_other"], low)
        return out

    solver = module.net.simulator.contact_model.solver  # (the module's, which counts and continues on failure)
    solver.reset()
    least_norm._analyse = recording
    try:
        with torch.no_grad():
            for batch in data.train_dataloader():
                module.loss(batch)
    finally:
        least_norm._analyse = analyse
    stats["problems"] = solver.problems
    stats["status"] = {s.name: int(solver.counts[s]) for s in Status}
    if ratios:
        r = torch.cat(ratios)
        stats["flat_part_of_q"] = {f"<= {t:g}": int((r <= t).sum()) for t in (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)}
        stats["flat_part_of_q_max"] = float(r.max())
    return stats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--data", default="data")
    args = parser.parse_args()
    config = json.loads((args.run / "config.json").read_text())
    learned = json.loads((args.run / "learned.json").read_text())
    hp = config["args"]
    data = ContactDataModule(hp["task"], args.data, seed=hp["seed"])
    best = ContactLightningModule.from_checkpoint(learned["best_checkpoint"])
    initial = ContactLightningModule(best.config)
    for name, module in (("initial model", initial), ("best checkpoint", best)):
        print(name, json.dumps(replay(module, data)))


if __name__ == "__main__":
    main()
