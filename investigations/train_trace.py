"""Train as `diffcontact train` does, and keep what a run's log does not: every step's loss and gradient norms,
and a checkpoint every K epochs.

    python investigations/train_trace.py Rope --data runs/noise-0.05/data --out runs/trace-rope --every 5
    python investigations/checkpoint_criteria.py runs/trace-rope --data runs/noise-0.05/data

Written to find where a run's parameters jump (a loss that rises from one epoch to the next, masses that move by a
third in an epoch): `OUT/trace.csv` has one row per optimiser step (epoch, batch, loss, the gradient's norm over
all parameters and over each group: the potential network, the masses and inertia, μ and e, the learning rate), and
`OUT/checkpoints/trace/epoch=E.ckpt` the model every K epochs (all kept), and `OUT/spike-*.pt` the module's
state as it entered a step whose gradient norm was a spike, with its batch (investigations/gradient_spike.py). The
run itself is the same as `diffcontact train TASK --data DATA --out OUT` with the same settings (the extra callbacks
only read).
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (before torch: it sets OpenMP's wait policy)

# isort: split

import argparse
import csv
from pathlib import Path

import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

import diffcontact.train.run as run_module
from diffcontact.solver.problem import solve_cone_qp
from diffcontact.train.module import ContactLightningModule


def nearest_feasible(detector, x: torch.Tensor, iterations: int = 200, reach: float = 0.005) -> torch.Tensor:
    """Positions (B, P, d) near x (B, P, d) whose every gap is ≥ 0, by up to ``iterations`` linearised steps:
    dx = J_Cᵀλ with λ = argmin ½λᵀ(J_C J_Cᵀ)λ + gᵀλ, λ ≥ 0 (the least ‖dx‖ with g + J_C dx ≥ 0; the contact solver,
    frictionless), each step shortened to move no point more than ``reach`` (m: a bend limit crossed by radians is
    far from linear); on free points (the balls, the rope)."""
    x = x.detach().double().clone()
    for _ in range(iterations):
        contacts = detector.detect(x)
        if contacts is None:
            break
        dc, J = contacts.dc, contacts.J.double()
        normal = J[:, ::dc]  # (B', K, D): the normal rows
        A = normal @ normal.mT
        zero = torch.zeros_like(contacts.gap, dtype=torch.float64)
        lam = solve_cone_qp(A, contacts.gap.double(), zero, None, contacts.active)  # (raises where a problem fails)
        step = (normal.mT @ lam[..., None]).reshape(x[contacts.index].shape)
        longest = step.norm(dim=-1).amax(-1).clamp_min(reach)  # (B',)
        x[contacts.index] += step * (reach / longest)[:, None, None]
    return x


def feasible_start(module: ContactLightningModule, data) -> None:
    """Start the learned first-state corrections of ``module`` at the nearest feasible state of each chunk's first
    frame (``nearest_feasible``), the velocities as recorded."""
    detector = module.task.system.detector
    for split, states in module.first_states.items():
        if states.coords is not None:
            raise SystemExit("--feasible-start: first states in noise coordinates are not supported")
        x0 = data.splits[split].chunk_x[:, 0]
        states.dx.copy_((nearest_feasible(detector, x0) - x0.double()).to(states.dx))


class StepTrace(pl.Callback):
    """One CSV row per optimiser step: the loss and the gradient norms by parameter group."""

    def __init__(self, path: Path, spike: float, keep: int) -> None:
        self.path = path
        self.file = None
        self.writer = None
        self.norms: dict[str, float] = {}
        self.spike, self.keep, self.kept = spike, keep, 0
        self.recent: list[float] = []  # (the last 50 steps' gradient norms)
        self.before: tuple | None = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.kept < self.keep:  # (the module as it enters the step, to save with the batch if the step spikes)
            state = {k: t.detach().clone() for k, t in pl_module.state_dict().items()}
            self.before = (state, [t.clone() for t in batch])

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        groups: dict[str, float] = {}
        for name, p in pl_module.named_parameters():
            if p.grad is None:
                continue
            last = name.split(".")[-1]
            key = "mu_e" if last in ("mu_raw", "e_raw") else "mass" if last.startswith("log_") else "potential"
            groups[key] = groups.get(key, 0.0) + float(p.grad.double().square().sum())
        self.norms = {k: v**0.5 for k, v in groups.items()}
        self.norms["total"] = sum(groups.values()) ** 0.5
        self.norms["lr"] = optimizer.param_groups[0]["lr"]
        total = self.norms["total"]
        if len(self.recent) >= 20 and total > self.spike * sorted(self.recent)[len(self.recent) // 2]:
            if self.before is not None and self.kept < self.keep:
                name = f"spike-epoch{trainer.current_epoch}-step{trainer.global_step}.pt"
                torch.save(
                    {
                        "state_dict": self.before[0],
                        "batch": self.before[1],
                        "norm": total,
                        "median": sorted(self.recent)[len(self.recent) // 2],
                    },
                    self.path.parent / name,
                )
                self.kept += 1
        self.recent = (self.recent + [total])[-50:]

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        row = {
            "epoch": trainer.current_epoch,
            "batch": batch_idx,
            "loss": float(outputs["loss"] if isinstance(outputs, dict) else outputs),
        } | self.norms
        if self.writer is None:
            new = not self.path.exists()
            self.file = self.path.open("a", newline="")
            fields = ["epoch", "batch", "loss", "total", "potential", "mass", "mu_e", "lr"]
            self.writer = csv.DictWriter(self.file, fields, restval="")
            if new:
                self.writer.writeheader()
        self.writer.writerow(row)
        self.file.flush()
        self.norms = {}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task")
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--model", default=None)
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--every", type=int, default=5, help="a kept checkpoint every this many epochs")
    parser.add_argument("--resume", action="store_true")
    parser.add_argument(
        "--spike",
        type=float,
        default=20.0,
        help="a step whose gradient norm is this many times "
        "the median of the last 50 is a spike: the module before it and its batch are saved",
    )
    parser.add_argument("--keep", type=int, default=10, help="spikes saved at most")
    parser.add_argument(
        "--feasible-start",
        action="store_true",
        help="first-state corrections start at the nearest state that meets every limit",
    )
    args = parser.parse_args()
    out = Path(args.out)
    made = run_module._trainer

    def traced(*a, **k):
        trainer, checkpoints = made(*a, **k)
        trainer.callbacks.append(StepTrace(out / "trace.csv", args.spike, args.keep))
        trainer.callbacks.append(
            ModelCheckpoint(dirpath=out / "checkpoints" / "trace", filename="{epoch}", save_top_k=-1,
                            every_n_epochs=args.every, enable_version_counter=False)
        )  # fmt: skip
        return trainer, checkpoints

    run_module._trainer = traced
    if args.feasible_start:
        started = ContactLightningModule.on_fit_start

        def on_fit_start(module: ContactLightningModule) -> None:
            started(module)
            if module.current_epoch == 0 and module.first_states:
                feasible_start(module, module.trainer.datamodule)

        ContactLightningModule.on_fit_start = on_fit_start
    torch.set_num_threads(1)
    run_module.train_run(args.task, args.model, out=out, resume=args.resume, progress=False, data_root=args.data,
                         seed=args.seed)  # fmt: skip


if __name__ == "__main__":
    main()
