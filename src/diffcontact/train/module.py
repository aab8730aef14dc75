"""Lightning module: one of the four models trained on 5-frame chunks (paper Sec. 5, spec E).

L1 loss on the predicted chunk (positions and velocities of every point, frame 0 included as published), AdamW
(lr 1e-3, weight decay 1e-4).  Optimisation is manual so that a step whose gradients are not finite is skipped
entirely (no update, no weight decay, no moment update) and counted.  Logged per epoch: losses, learned μ and e
(summary), learned mass ratios, skipped steps and contact-solver failures.
"""

from __future__ import annotations

from collections import Counter

import lightning.pytorch as pl
import torch

from diffcontact.errors import ConfigError
from diffcontact.models import BASELINE_NAMES, build_model
from diffcontact.solver import ContactSolver
from diffcontact.systems.registry import build_task

SCHEDULES = ("constant", "cosine")  # of the learning rate over the epochs
TRAIN_LOSSES = ("l1", "mse")  # the training loss; validation is always L1 (val/loss, checkpoint selection)


class ContactLightningModule(pl.LightningModule):
    """Trains ``model`` (one of ``diffcontact.models.MODEL_NAMES``) on the chunks of ``task``, or a baseline
    (``BASELINE_NAMES``) on their one-step pairs (batches of ``PairDataset``)."""

    def __init__(
        self,
        task: str,
        model: str = "CM-CD-CLNN",
        lr: float = 1e-3,
        weight_decay: float = 1e-4,
        mu_transform: str = "projected",
        e_transform: str = "projected",
        hidden: int = 256,
        layers: int = 3,
        seed: int = 0,
        dtype: str = "float32",
        schedule: str = "constant",
        coef_lr: float = 1.0,
        mu_coef_lr: float | None = None,
        reg: float | None = None,
        train_loss: str = "l1",
    ):
        super().__init__()
        if schedule not in SCHEDULES:
            raise ConfigError(f"schedule = {schedule!r} is not one of {list(SCHEDULES)}")
        if train_loss not in TRAIN_LOSSES:
            raise ConfigError(f"train_loss = {train_loss!r} is not one of {list(TRAIN_LOSSES)}")
        self.save_hyperparameters()
        self.automatic_optimization = False
        self.task = build_task(task)
        self.solver = ContactSolver(on_failure="count")  # (continues with zero impulses, counts and logs failures)
        self._failures_before: Counter[str] = Counter()  # (restored from a checkpoint)
        self.skipped_steps = 0
        net = build_model(
            self.task,
            model,
            mu_transform=mu_transform,
            e_transform=e_transform,
            hidden=hidden,
            layers=layers,
            seed=seed,
            solver=self.solver,
            reg=reg,
        )
        self.net = net.to(getattr(torch, dtype))
        self.baseline = model in BASELINE_NAMES
        self.learns_contacts = self.learned is not None and self.learned.n_slots > 0  # (μ and e)

    @property
    def learned(self):
        """The net's learned physical parameters (LearnedParams), or None (IN-CP-SP learns none)."""
        return self.net.params

    @property
    def solver_failures_by_status(self) -> Counter[str]:
        """Contact problems the solver failed on so far, by status name (resumed runs: over all sessions)."""
        return self._failures_before + Counter(self.solver.failures_by_status)

    @property
    def solver_failures(self) -> int:
        """Contact problems the solver failed on so far (impulses replaced by zeros)."""
        return sum(self.solver_failures_by_status.values())

    def loss(self, batch, kind: str | None = None) -> torch.Tensor:
        """Mean absolute (``kind`` "l1") or squared ("mse") error of the predicted chunk: x, v (B, L, P, d); a
        baseline's one-step pair (x0, v0, x1, v1, ...) is the chunk of its two frames.  ``kind`` None: the
        ``train_loss`` in training mode, L1 otherwise (validation)."""
        kind = kind or (self.hparams.train_loss if self.training else "l1")
        x, v = batch[0], batch[1]
        if self.baseline:
            x, v = torch.stack([batch[0], batch[2]], 1), torch.stack([batch[1], batch[3]], 1)
        px, pv = self.net(x[:, 0], v[:, 0], x.shape[1])
        err = (lambda r: r.abs()) if kind == "l1" else torch.square
        return 0.5 * (err(px - x).mean() + err(pv - v).mean())

    def training_step(self, batch, batch_idx: int):
        opt = self.optimizers()
        loss = self.loss(batch)
        opt.zero_grad()
        self.manual_backward(loss)
        grads = [p.grad for p in self.net.parameters() if p.grad is not None]
        if all(bool(torch.isfinite(g).all()) for g in grads) and bool(torch.isfinite(loss)):
            opt.step()
            if self.learns_contacts:
                self.learned.project_()
        else:  # skipped entirely: no update, no weight decay
            self.skipped_steps += 1
            opt.zero_grad()
        self.log("train/loss", loss.detach(), prog_bar=True, on_step=False, on_epoch=True, batch_size=batch[0].shape[0])
        return loss.detach()

    def validation_step(self, batch, batch_idx: int):
        loss = self.loss(batch)
        self.log("val/loss", loss, prog_bar=True, on_epoch=True, batch_size=batch[0].shape[0])
        return loss

    def on_train_epoch_end(self) -> None:
        self.log("train/lr", self.optimizers().param_groups[0]["lr"])  # (the rate this epoch used)
        if self.hparams.schedule != "constant":  # (manual optimisation: the schedule is stepped here)
            self.lr_schedulers().step()
        p = self.learned
        if self.learns_contacts:
            means = {"learned/mu_mean": p.mu.detach().mean(), "learned/e_mean": p.e.detach().mean()}
            self.log_dict(means, prog_bar=True)
        self.log_dict(
            {
                "train/skipped_steps": float(self.skipped_steps),
                "train/solver_failures": float(self.solver_failures),
            }
        )
        if p is not None:
            for i, r in enumerate(self.mass_ratio().tolist()):
                self.log(f"learned/mass_ratio_{i}", r)

    def mass_ratio(self) -> torch.Tensor:
        """Learned masses divided by the first body's: (n_bodies,)."""
        m = self.learned.inertia.masses.detach()
        return m / m[0]

    def configure_optimizers(self):
        # e (and μ unless mu_coef_lr is given) at coef_lr × lr: Adam moves a parameter about lr per step, whatever
        # its gradient's size
        p, hp = self.learned, self.hparams
        mu_coef = hp.coef_lr if hp.mu_coef_lr is None else hp.mu_coef_lr
        coefs = {id(p.mu_raw), id(p.e_raw)} if self.learns_contacts else set()
        groups = [{"params": [t for t in self.net.parameters() if id(t) not in coefs]}]
        if self.learns_contacts:
            groups += [
                {"params": [p.mu_raw], "lr": hp.lr * mu_coef},
                {"params": [p.e_raw], "lr": hp.lr * hp.coef_lr},
            ]
        opt = torch.optim.AdamW(groups, lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        epochs = self.trainer.max_epochs if self._trainer is not None and self.trainer.max_epochs else 1
        if self.hparams.schedule == "constant":
            return opt
        # cosine from lr to lr/100 over the run's epochs (stepped at each epoch's end)
        cosine = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs, eta_min=self.hparams.lr / 100)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": cosine, "interval": "epoch"}}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["counters"] = {
            "skipped_steps": self.skipped_steps,
            "solver_failures_by_status": dict(self.solver_failures_by_status),
        }

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        counters = checkpoint.get("counters", {})
        self.skipped_steps = counters.get("skipped_steps", 0)
        # (checkpoints before the count by status hold the total only)
        old = {"unknown": counters["solver_failures"]} if counters.get("solver_failures") else {}
        self._failures_before = Counter(counters.get("solver_failures_by_status", old))
        self.solver.reset()
