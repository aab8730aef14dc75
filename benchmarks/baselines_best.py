"""The paper's baselines at their best: each trained over a grid of training settings, the setting and the
checkpoint chosen on the validation trajectories, and every run scored on the test trajectories beside a
constant-velocity predictor (docs/baselines.md, "At their best").

    diffcontact generate BP5-e --out data
    python benchmarks/baselines_best.py BP5-e --out runs/baselines-best -j 2
    python benchmarks/baselines_best.py BP5 --losses mse --lrs 0.001    # one setting of the grid

The grid is the training loss (L1, the paper's; MSE) × the learning rate (1e-2, the default preset's; 1e-3, the
paper's), cosine schedule, ``--epochs`` each.  Two checkpoints of a run are scored, the one it chose on its
validation loss and its last.  Each is scored on the validation split by the 5-step error of Fig. 3
(``diffcontact.eval.metrics``) and by the one-step error on the pairs whose second frame holds a collision (the
relative error of the state, as Fig. 3 measures it), both against a constant-velocity predictor (x' = x + v dt,
v' = v) and the collapse level (the true smooth flow with no velocity jump: what a CLNN baseline whose flow is
right and whose jump is 0 scores) on the same frames: a model whose collision response is learned is below them.
Every run is a resumable run directory (OUT/TASK/MODEL/LOSS-lrLR); a finished one is not trained again.  Prints a
markdown table of every run and writes it to OUT/TASK/best.md, with the setting chosen for each model in
OUT/TASK/best.json.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
import re
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path

import torch

from diffcontact.bench.train import NoContacts
from diffcontact.data.dataset import PairDataset
from diffcontact.data.store import dataset_folder, load_split
from diffcontact.eval.loading import load_run
from diffcontact.eval.metrics import mean_interval, relative_error, trajectory_error
from diffcontact.eval.rollouts import ground_truth, predict
from diffcontact.files import write_json, write_text
from diffcontact.models import BASELINE_NAMES
from diffcontact.run_dir import RunDir
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.train.run import train_run

LOSSES = ("l1", "mse")
LRS = (1e-2, 1e-3)


def run_dir(out: Path, task: str, model: str, loss: str, lr: float) -> Path:
    return out / task / model / f"{loss}-lr{lr:g}"


def train_one(cell: tuple) -> str:
    """Train one (task, model, loss, lr) run into its directory (resumed if it was cut off); its path."""
    torch.set_num_threads(1)
    task, model, loss, lr, epochs, data, path = cell
    run = RunDir(path)
    if run.learned.is_file():
        return str(path)
    resume = run.last_checkpoint.is_file()
    train_run(task, model, out=path, resume=resume, progress=False, epochs=epochs, lr=lr, train_loss=loss,
              schedule="cosine", data_root=data)  # fmt: skip
    return str(path)


def constant_velocity(x0: torch.Tensor, v0: torch.Tensor, frames: int, dt: float):
    """x_t = x0 + t dt v0, v_t = v0: (N, frames, P, d) each."""
    t = torch.arange(frames, dtype=x0.dtype)[None, :, None, None] * dt
    return x0[:, None] + t * v0[:, None], v0[:, None].expand(-1, frames, -1, -1)


def no_jump(task, x0: torch.Tensor, v0: torch.Tensor, frames: int):
    """The collapse level's rollout: the task's simulator with true parameters and contacts disabled (its smooth
    flow alone)."""
    sim = simulator_for(task)
    bare = replace(sim, system=replace(sim.system, detector=NoContacts()))
    with torch.no_grad():
        xs, vs, _ = bare.rollout(State(x0, v0), task.params, task.dt, frames)
    return xs, vs


def five_step(x_hat, v_hat, x, v) -> tuple[float, float | None, int]:
    """Fig. 3's 5-step error (mean, 95 % half-width) and the trajectories that diverged."""
    rel = relative_error(x_hat, v_hat, x, v, diverged_ok=True)
    mean, half = mean_interval(trajectory_error(rel, 5))
    return mean, half, int((~torch.isfinite(rel)).any(1).sum())


def collision_pairs(net, folder: Path, split: str, task) -> dict:
    """One-step relative error on the split's pairs with a collision: the model's, constant velocity's and the
    collapse level's (means)."""
    pairs = PairDataset(load_split(folder, split, task.config))
    hit = pairs.collision
    x0, v0, x1, v1 = (t[hit].double() for t in (pairs.x0, pairs.v0, pairs.x1, pairs.v1))
    xh, vh = predict(net, x0, v0, 2)
    xc, vc = constant_velocity(x0, v0, 2, float(pairs.dt))
    truth = (x1[:, None], v1[:, None])
    model = relative_error(xh[:, 1:], vh[:, 1:], *truth, diverged_ok=True)[:, 0]
    const = relative_error(xc[:, 1:], vc[:, 1:], *truth)[:, 0]
    xn, vn = no_jump(task, x0, v0, 2)
    level = relative_error(xn[:, 1:], vn[:, 1:], *truth)[:, 0]
    return {
        "pairs": int(hit.sum()),
        "model": float(model.mean()),
        "constant_velocity": float(const.mean()),
        "no_jump": float(level.mean()),
    }


def score(path: Path, checkpoint: Path, split: str, data: str) -> dict:
    """A checkpoint of the run on ``split``: 5-step error and collision-pair error, each beside constant velocity
    and the collapse level."""
    loaded = load_run(path, checkpoint=checkpoint)
    net, task, config = loaded.net, loaded.task, loaded.task.config
    folder = dataset_folder(data, loaded.task_name)
    x, v, _, dt = ground_truth(folder, split, 5, config)
    xh, vh = predict(net, x[:, 0], v[:, 0], 5)
    xc, vc = constant_velocity(x[:, 0], v[:, 0], 5, dt)
    mean, half, diverged = five_step(xh, vh, x, v)
    const, _, _ = five_step(xc, vc, x, v)
    level, _, _ = five_step(*no_jump(task, x[:, 0], v[:, 0], 5), x, v)
    return {
        "checkpoint": checkpoint.name,
        "five_step": mean,
        "ci95": half,
        "diverged": diverged,
        "constant_velocity": const,
        "no_jump": level,
        "collision_pairs": collision_pairs(net, folder, split, task),
    }


def checkpoints(path: Path) -> dict[str, Path]:
    """The checkpoint the run chose on its validation loss (what training keeps) and its last one."""
    run = RunDir(path)
    return {"chosen": run.best_checkpoint(), "last": run.last_checkpoint}


def _epoch(checkpoint: Path) -> int | str:
    """The epoch of a checkpoint (the last one's from its own record)."""
    found = re.search(r"epoch=(\d+)", checkpoint.name)
    if found:
        return int(found.group(1))
    return int(torch.load(checkpoint, map_location="cpu", weights_only=False)["epoch"])


def _diverged(scored: dict) -> str:
    return f" ({scored['diverged']} diverged)" if scored["diverged"] else ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task")
    parser.add_argument("--models", default=",".join(BASELINE_NAMES))
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--data", default="data")
    parser.add_argument("--out", default="runs/baselines-best")
    parser.add_argument("--losses", default=",".join(LOSSES), help="the grid's training losses")
    parser.add_argument("--lrs", default=",".join(f"{lr:g}" for lr in LRS), help="the grid's learning rates")
    parser.add_argument("-j", "--jobs", type=int, default=1)
    args = parser.parse_args()
    out, models = Path(args.out), args.models.split(",")
    losses, lrs = args.losses.split(","), [float(lr) for lr in args.lrs.split(",")]
    cells = [(args.task, m, loss, lr, args.epochs, args.data, run_dir(out, args.task, m, loss, lr))
             for m in models for loss in losses for lr in lrs]  # fmt: skip
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        for done in pool.map(train_one, cells):
            print("trained", done, flush=True)
    rows, best = [], {}
    header = (
        "| model | loss | lr | checkpoint | val 5-step | val collision pairs (constant velocity; no jump) "
        "| test 5-step (± 95 %) | test collision pairs (constant velocity; no jump) |\n"
        "|---|---|---|---|---|---|---|---|"
    )
    for m in models:
        scored = []
        for loss in losses:
            for lr in lrs:
                path = run_dir(out, args.task, m, loss, lr)
                for which, ckpt in checkpoints(path).items():
                    val, test = score(path, ckpt, "val", args.data), score(path, ckpt, "test", args.data)
                    scored.append((val["five_step"], loss, lr, which, val, test))
                    vc, tc = val["collision_pairs"], test["collision_pairs"]
                    rows.append(
                        f"| {m} | {loss} | {lr:g} | {which} (epoch {_epoch(ckpt)}) | {val['five_step']:.4g} "
                        f"| {vc['model']:.4g} ({vc['constant_velocity']:.4g}; {vc['no_jump']:.4g}) "
                        f"| {test['five_step']:.4g} ± {test['ci95']:.2g}{_diverged(test)} "
                        f"| {tc['model']:.4g} ({tc['constant_velocity']:.4g}; {tc['no_jump']:.4g}) |"
                    )
        chosen = min(scored, key=lambda s: s[0])
        best[m] = dict(zip(("loss", "lr", "checkpoint", "val", "test"), chosen[1:]))
    ref = best[models[0]]["test"]
    table = header + "\n" + "\n".join(rows)
    table += f"\n\ntest 5-step: constant velocity {ref['constant_velocity']:.4g}, no jump {ref['no_jump']:.4g}\n"
    chosen = (f"{m} {b['loss']} lr {b['lr']:g} {b['checkpoint']}" for m, b in best.items())
    table += "chosen on validation: " + ", ".join(chosen) + "\n"
    print(table)
    write_text(out / args.task / "best.md", table)
    write_json(out / args.task / "best.json", best)


if __name__ == "__main__":
    main()
