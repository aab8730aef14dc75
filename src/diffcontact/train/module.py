"""Lightning module: one of the four models trained on 5-frame chunks (paper Sec. 5).

L1 loss on the predicted chunk (positions and velocities of every point, frame 0 included as published), AdamW; the
rates, the schedule and every other setting are the run's :class:`~diffcontact.train.config.TrainConfig`, the
module's one settings argument.  Optimisation is manual so that a step whose gradients are not finite is skipped
entirely (no update, no weight decay, no moment update) and counted; so is a step whose forward pass fails on a
non-finite state (a diverging learned model), with a warning.  Logged per epoch: losses, learned μ and e (summary),
learned mass ratios, skipped steps and contact-solver failures.

On data recorded with observation noise (``first_state_chunks`` > 0), the first state of every training and
validation chunk is learned with the model (:mod:`diffcontact.train.first_states`): a training batch moves its
chunks' first states with the model's step, a validation batch its chunks' first states alone (one step, the model
fixed), so that the validation loss, which chooses the checkpoint and stops the run, is the same loss as the
training's, least over the first states.

On several processes (DDP) gradients are averaged over them, so a step is skipped on all or none: a process whose
forward pass failed contributes NaN gradients.  Skipped steps are therefore the same on every process; forward and
solver failures are each process's own and are summed over the processes (``totals``).
"""

from __future__ import annotations

import logging
import time
import warnings
from collections import Counter
from pathlib import Path
from typing import cast

import lightning.pytorch as pl
import torch
from lightning.pytorch.core.optimizer import LightningOptimizer
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

from diffcontact.models import BASELINE_NAMES, LearnedParams, build_model
from diffcontact.solver import ContactSolver, Status
from diffcontact.solver.status import is_failure
from diffcontact.systems.base import Task
from diffcontact.systems.registry import build_task
from diffcontact.train.config import TrainConfig
from diffcontact.train.first_states import FirstStates

log = logging.getLogger(__name__)

KEEP_FAILED = 100  # failed contact problems a training run keeps for diagnosis (RUN/solver_failures.npz)

_FAILED = [s.name for s in Status if is_failure(s)]  # (the statuses counted as solver failures)


class _NoAdvertisement(logging.Filter):
    """Drops Lightning's "💡 Tip" advertisement (litlogger, its cloud service) from its rank-zero log."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("💡 Tip")


_QUIET = _NoAdvertisement()


def quiet_lightning() -> None:
    """Lightning's advertisement, its use of a name that torch has deprecated (``LeafSpec``) and its notice that a
    resumed run's checkpoint folder is not empty, none of which a user can act on, silenced where they come from;
    every other message and warning stays."""
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logger = logging.getLogger(name)
        if _QUIET not in logger.filters:
            logger.addFilter(_QUIET)
    warnings.filterwarnings(
        "ignore", r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning, r"lightning\.pytorch\."
    )
    # (a resumed run's checkpoint folder is not empty by design; a fresh run into one is refused before Lightning)
    warnings.filterwarnings("ignore", r"Checkpoint directory .* exists and is not empty", UserWarning)


def saved_config(checkpoint: dict) -> TrainConfig:
    """The settings a loaded Lightning checkpoint of the module holds: its run's ``TrainConfig`` record, or, in one
    written when the module took keyword arguments, the task, the model and the settings given (TrainConfig's
    defaults for the rest, as that module took them)."""
    saved = dict(checkpoint.get("hyper_parameters", {}))
    return TrainConfig.from_record(saved["config"]) if "config" in saved else TrainConfig(**saved)


class ContactLightningModule(pl.LightningModule):
    """Trains ``model`` (one of ``diffcontact.models.MODEL_NAMES``) on the chunks of ``task``, or a baseline
    (``BASELINE_NAMES``) on their one-step pairs (batches of ``PairDataset``)."""

    def __init__(self, config: TrainConfig | dict, *, built_task: Task | None = None):
        """``config``: the run's settings (a ``TrainConfig``, or its ``record()`` as a checkpoint holds it).
        ``built_task``: ``config.task`` already built (``build_task``, by a caller that has parsed the task file), used
        instead of building it again; not a hyperparameter (a checkpoint records the task, which builds it)."""
        super().__init__()
        quiet_lightning()  # (the module is what brings Lightning in: its notices are quieted wherever it is used)
        if not isinstance(config, (TrainConfig, dict)):
            raise TypeError(f"config is a TrainConfig or its record, not {config!r}: e.g. TrainConfig('BP1')")
        self.config = config if isinstance(config, TrainConfig) else TrainConfig.from_record(config)
        self.save_hyperparameters({"config": self.config.record()})  # (what load_from_checkpoint passes back)
        self.automatic_optimization = False
        self.task = build_task(self.config.task) if built_task is None else built_task
        # (continues with zero impulses, counts and logs failures, and keeps the first ones: RUN/solver_failures.npz)
        self.solver = ContactSolver(on_failure="count", keep=KEEP_FAILED)
        self._failures_before: Counter[str] = Counter()  # (restored from a checkpoint)
        self.skipped_steps = 0  # (optimiser steps skipped: the same on every process)
        self.forward_failures = 0  # (this process's)
        self.seconds_before = 0.0  # (the wall time of a resumed run's earlier sessions, from its checkpoint)
        self._fit_started = time.perf_counter()
        c, model = self.config, self.config.model
        net = build_model(
            self.task,
            model,
            mu_transform=c.mu_transform,
            e_transform=c.e_transform,
            hidden=c.hidden,
            layers=c.layers,
            seed=c.seed,
            solver=self.solver,
            reg=c.reg or None,  # (recorded 0 for the exact models: none)
            moments_init=c.moments_init,  # (the bodies' size², for every model that learns an inertia)
            # (the potential is the contact models' setting: a baseline learns its own network)
            **({} if model in BASELINE_NAMES else {"potential": c.potential}),
        )
        self.net = net.to(getattr(torch, c.dtype))
        q, n_points = self.task.system.points_per_body, self.task.system.n_points
        axis = (torch.arange(n_points) % q) > 0  # (an extended body's axis points: all but its first)
        self._point_scale = torch.where(axis, float(c.axis_scale), 1.0)
        self.baseline = model in BASELINE_NAMES
        self.learns_contacts = self.learned is not None and self.learned.n_slots > 0  # (μ and e)
        self.first_states: dict[str, FirstStates] = {}
        if c.first_state_chunks:  # (the chunks' first states, learned: see the module docstring)
            dtype, coords = getattr(torch, c.dtype), self.task.system.noise_coordinates
            shape = (n_points, self.task.system.d) if coords is None else (coords.size,)
            self.first_train = FirstStates(c.first_state_chunks, shape, dtype, coords)
            self.first_val = FirstStates(c.first_state_val_chunks, shape, dtype, coords)
            self.first_states = {"train": self.first_train, "val": self.first_val}

    @classmethod
    def from_checkpoint(cls, path: str | Path, built_task: Task | None = None) -> ContactLightningModule:
        """The module saved in the Lightning checkpoint ``path``, on the CPU, with its settings (``saved_config``),
        weights and counters."""
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
        module = cls(saved_config(checkpoint), built_task=built_task)
        module.on_load_checkpoint(checkpoint)
        module.load_state_dict(checkpoint["state_dict"])
        return module

    @property
    def learned(self) -> LearnedParams | None:
        """The net's learned physical parameters (LearnedParams), or None (IN-CP-SP learns none)."""
        params = self.net.params
        if params is not None and not isinstance(params, LearnedParams):  # (build_model's nets learn theirs)
            raise TypeError(f"the net's params are {type(params).__name__}, not LearnedParams")
        return params

    @property
    def _params(self) -> LearnedParams:
        """``learned``, of a model known to learn physical parameters (e.g. ``learns_contacts``)."""
        params = self.learned
        if params is None:
            raise TypeError(f"{self.config.model} learns no physical parameters")
        return params

    def _optimizer(self) -> LightningOptimizer:
        """The one optimiser of ``configure_optimizers``."""
        opt = self.optimizers()
        if isinstance(opt, list):
            raise TypeError(f"expected one optimiser, got {len(opt)}")
        return opt

    @property
    def solver_failures_by_status(self) -> Counter[str]:
        """Contact problems the solver failed on so far, by status name (resumed runs: over all sessions)."""
        return self._failures_before + Counter(self.solver.failures_by_status)

    @property
    def solver_failures(self) -> int:
        """Contact problems the solver failed on so far in this process (impulses replaced by zeros)."""
        return sum(self.solver_failures_by_status.values())

    def totals(self) -> dict:
        """The counters of the run, summed over its processes (a collective call on several: every process calls it):
        skipped_steps, forward_failures, solver_failures and solver_failures_by_status."""
        names = [*_FAILED, "unknown"]  # (the same on every process; "unknown": counts of old checkpoints)
        local = torch.tensor(
            [self.forward_failures, *(self.solver_failures_by_status[n] for n in names)], dtype=torch.float64
        )
        summed = local
        if self._trainer is not None and self.trainer.world_size > 1:
            summed = self.trainer.strategy.reduce(local.to(self.device), reduce_op="sum").cpu()
        by_status = {n: int(c) for n, c in zip(names, summed[1:].tolist()) if c}
        return dict(
            skipped_steps=self.skipped_steps,
            forward_failures=int(summed[0]),
            solver_failures=sum(by_status.values()),
            solver_failures_by_status=by_status,
        )

    def loss(self, batch, kind: str | None = None, first: tuple | None = None) -> torch.Tensor:
        """Mean absolute (``kind`` "l1") or squared ("mse") error of the predicted chunk: x, v (B, L, P, d); a
        baseline's one-step pair (x0, v0, x1, v1, ...) is the chunk of its two frames.  ``kind`` None: the run's
        ``train_loss``, in training and in validation (val/loss chooses the checkpoint by the objective the run
        minimises: an MSE run chosen by its L1 kept a worse model, docs/baselines.md).  ``first``: corrections dx,
        dv of the chunks' first frames (learned first states: ``FirstStates.start``), or None."""
        return self._losses(batch, kind, first)[0]

    def _losses(self, batch, kind: str | None, first: tuple | None) -> tuple[torch.Tensor, torch.Tensor]:
        """``loss`` and each chunk's share of it (B,) without the pull of μ (their mean is the data term)."""
        kind = kind or self.config.train_loss
        x, v = batch[0], batch[1]
        if self.baseline:
            x, v = torch.stack([batch[0], batch[2]], 1), torch.stack([batch[1], batch[3]], 1)
        x0, v0 = (x[:, 0], v[:, 0]) if first is None else self.first_train.start(x[:, 0], v[:, 0], *first)
        px, pv = self.net(x0, v0, x.shape[1])
        err = (lambda r: r.abs()) if kind == "l1" else torch.square
        w = self.config.velocity_weight
        scale = self._point_scale.to(x)[:, None]  # (P, 1): 1 at each body's centre, axis_scale at its axis points
        chunks = (err(scale * (px - x)).flatten(1).mean(1) + w * err(scale * (pv - v)).flatten(1).mean(1)) / (1.0 + w)
        loss = chunks.mean()
        if self.training and self.config.mu_l1 and self.learns_contacts:
            # a constant pull of every μ toward 0: where all of a slot's contacts stick the data give μ no gradient
            # (a plateau above the truth), and Adam moves μ down at its full rate until they slide again
            loss = loss + self.config.mu_l1 * self._params.mu.sum()
        return loss, chunks

    def as_fitted(self, split: str, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The chunks x, v (N, L, P, d) of ``split`` ("train" or "val"), all of them in order, as the model is fitted
        to them: their first frames corrected by the learned first states where the run learns them."""
        states = self.first_states.get(split)
        return (x, v) if states is None else states.corrected(x, v)

    def _first(self, batch, split: str) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The learned first-state corrections of a chunk batch of ``split`` (leaves), or None."""
        states = self.first_states.get(split)
        return None if states is None or len(batch) != 5 else states.take(batch[4])

    def _move_first(self, batch, split: str, first, grads, chunks: torch.Tensor) -> None:
        """One step of the first states ``first`` of a chunk batch of ``split``, whose losses are ``chunks`` (B,),
        along ``grads``, at the schedule's share of ``first_state_lr``; none, with a warning, where a gradient is not
        finite."""
        if first is None:
            return
        if any(g is None or not bool(torch.isfinite(g).all()) for g in grads):
            log.warning("epoch %d: the %s chunks' first states of a batch kept: a gradient is not finite",
                        self.current_epoch, split)  # fmt: skip
            return
        share = self._optimizer().param_groups[0]["lr"] / self.config.lr  # (the schedule's decay so far)

        def loss_at(dx: torch.Tensor, dv: torch.Tensor) -> torch.Tensor:  # (the chunks' losses, this model)
            try:
                return self._losses(batch, None, (dx, dv))[1]
            except FloatingPointError:  # (a trial state the model cannot step: not taken)
                return torch.full_like(chunks, float("inf"))

        with torch.no_grad():
            lr = self.config.first_state_lr * share
            self.first_states[split].update(batch[4], grads[0], grads[1], lr, chunks, loss_at)

    def training_step(self, batch, batch_idx: int):
        opt = self._optimizer()
        first = self._first(batch, "train")
        try:
            loss, chunks = (self.loss(batch), None) if first is None else self._losses(batch, None, first)
            failed = None
        except FloatingPointError as err:  # (a non-finite state in the forward pass: this step is skipped)
            self.forward_failures += 1
            failed, chunks = err, None
            # (NaN gradients: skipped everywhere; a Tensor, the net having parameters)
            loss = cast(torch.Tensor, float("nan") * sum(p.sum() for p in self.net.parameters()))
        opt.zero_grad()
        self.manual_backward(loss)
        grads = [p.grad for p in self.net.parameters() if p.grad is not None]
        if all(bool(torch.isfinite(g).all()) for g in grads) and bool(torch.isfinite(loss)):
            if first is not None:  # (before the model's step: a trial is scored under the model of the gradients)
                self._move_first(batch, "train", first, [t.grad for t in first], cast(torch.Tensor, chunks))
            opt.step()
            if self.learns_contacts:
                self._params.project_()
        else:  # skipped entirely: no update, no weight decay
            self.skipped_steps += 1
            opt.zero_grad()
            why = f"its forward pass failed ({failed})" if failed else "its loss or gradients are not finite"
            log.warning("epoch %d batch %d: training step skipped: %s", self.current_epoch, batch_idx, why)
        # (logged by every step, so that the processes of a DDP run average the same metric: a failed step with
        # weight 0, which leaves the epoch's mean to the others)
        value, n = (loss.detach(), len(batch[0])) if failed is None else (torch.zeros(()), 0)
        self.log("train/loss", value, prog_bar=True, on_step=False, on_epoch=True, batch_size=n, sync_dist=True)
        return loss.detach()

    def validation_step(self, batch, batch_idx: int):
        first = self._first(batch, "val")
        try:
            if first is None:
                loss = self.loss(batch)
            else:  # (its first states move one step along their own gradient; the model is fixed)
                with torch.enable_grad():
                    loss, chunks = self._losses(batch, None, first)
                    grads = torch.autograd.grad(loss, first, allow_unused=True)
                self._move_first(batch, "val", first, grads, chunks)
                loss = loss.detach()
        except FloatingPointError as err:  # (a diverging model: the worst loss, not a crash)
            self.forward_failures += 1
            log.warning(
                "epoch %d validation batch %d: forward pass failed (%s); loss inf", self.current_epoch, batch_idx, err
            )
            loss = torch.tensor(float("inf"))
        self.log("val/loss", loss, prog_bar=True, on_epoch=True, batch_size=batch[0].shape[0], sync_dist=True)
        return loss

    def on_train_epoch_end(self) -> None:
        # (the values below are the same on every process of a DDP run: sync_dist averages equal values)
        self.log("train/lr", self._optimizer().param_groups[0]["lr"], sync_dist=True)  # (the rate this epoch used)
        if self.config.schedule != "constant":  # (manual optimisation: the schedule is stepped here)
            schedule = self.lr_schedulers()
            if schedule is None or isinstance(schedule, (list, torch.optim.lr_scheduler.ReduceLROnPlateau)):
                raise TypeError(f"expected one epoch-wise schedule, got {schedule!r}")
            schedule.step()
        p = self.learned
        if self.learns_contacts:
            c = self._params
            means = {"learned/mu_mean": c.mu.detach().mean(), "learned/e_mean": c.e.detach().mean()}
            self.log_dict(means, prog_bar=True, sync_dist=True)
        totals = self.totals()
        self.log_dict(
            {
                "train/skipped_steps": float(totals["skipped_steps"]),
                "train/forward_failures": float(totals["forward_failures"]),
                "train/solver_failures": float(totals["solver_failures"]),
            },
            sync_dist=True,  # (already summed over the processes)
        )
        if p is not None:
            for i, r in enumerate(self.mass_ratio().tolist()):
                self.log(f"learned/mass_ratio_{i}", r, sync_dist=True)
            com = p.inertia.com  # (m, body frame: the box's)
            for i, body in enumerate([] if com is None else com.detach().tolist()):
                for axis, value in zip("xyz", body):
                    self.log(f"learned/centre_of_mass_{i}_{axis}", value, sync_dist=True)

    def mass_ratio(self) -> torch.Tensor:
        """Learned masses divided by the first body's: (n_bodies,)."""
        m = self._params.inertia.masses.detach()
        return m / m[0]

    def configure_optimizers(self) -> torch.optim.AdamW | OptimizerLRSchedulerConfig:
        # e (and μ unless mu_coef_lr is given) at coef_lr × lr: Adam moves a parameter about lr per step, whatever
        # its gradient's size
        p, hp = self._params if self.learns_contacts else None, self.config
        mu_coef = hp.coef_lr if hp.mu_coef_lr is None else hp.mu_coef_lr
        coefs = {id(p.mu_raw), id(p.e_raw)} if p is not None else set()
        groups = [{"params": [t for t in self.net.parameters() if id(t) not in coefs]}]
        if p is not None:
            groups += [
                {"params": [p.mu_raw], "lr": hp.lr * mu_coef},
                {"params": [p.e_raw], "lr": hp.lr * hp.coef_lr},
            ]
        opt = torch.optim.AdamW(groups, lr=hp.lr, weight_decay=hp.weight_decay)
        epochs = self.trainer.max_epochs if self._trainer is not None and self.trainer.max_epochs else 1
        if hp.schedule == "constant":
            return opt
        # cosine from lr to lr/100 over the run's epochs (stepped at each epoch's end)
        cosine = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs, eta_min=hp.lr / 100)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": cosine, "interval": "epoch"}}

    def on_fit_start(self) -> None:
        self._fit_started = time.perf_counter()

    def training_seconds(self) -> float:
        """Wall time of the training in s, over all its sessions (a resumed run counts its earlier ones)."""
        return self.seconds_before + time.perf_counter() - self._fit_started

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        totals = self.totals()  # (every process writes its checkpoint dictionary; rank 0 its file)
        checkpoint["counters"] = {
            k: totals[k] for k in ("skipped_steps", "forward_failures", "solver_failures_by_status")
        }
        checkpoint["counters"]["seconds"] = self.training_seconds()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        counters = checkpoint.get("counters", {})
        self.skipped_steps = counters.get("skipped_steps", 0)
        self.seconds_before = counters.get("seconds", 0.0)
        # (the run's totals continue on rank 0; checkpoints before the count by status hold the total only)
        first = self._trainer is None or self.global_rank == 0
        old = {"unknown": counters["solver_failures"]} if counters.get("solver_failures") else {}
        self.forward_failures = counters.get("forward_failures", 0) if first else 0
        self._failures_before = Counter(counters.get("solver_failures_by_status", old) if first else {})
        self.solver.reset()
