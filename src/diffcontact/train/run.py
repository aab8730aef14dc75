"""A training run: data, model, Lightning trainer, checkpoints, logs and the learned parameters."""

from __future__ import annotations

import json
import os
import time
from collections import Counter
from contextlib import nullcontext
from pathlib import Path

import lightning
import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger
from lightning.pytorch.plugins import TorchCheckpointIO
from lightning.pytorch.strategies import DDPStrategy
from lightning.pytorch.utilities import rank_zero_info

from diffcontact.config import TaskConfig, load_task
from diffcontact.data.noise import noise_kind
from diffcontact.data.store import load_meta
from diffcontact.errors import ConfigError
from diffcontact.eval.tosses import measured
from diffcontact.files import TMP_PREFIX, atomic_write, save_figure, versions, write_json
from diffcontact.lock import output_lock
from diffcontact.models import BASELINE_NAMES, MODEL_NAMES
from diffcontact.run_dir import BEST_CHECKPOINT, CALIBRATED_PREFIX, REFINED_PREFIX, RunDir
from diffcontact.solver.contact_solver import load_failed, save_failed
from diffcontact.systems.base import System
from diffcontact.systems.registry import build_task
from diffcontact.train.calibrate import calibrate_mu
from diffcontact.train.coef_start import scan_coefficients
from diffcontact.train.config import TrainConfig, check_given, task_training
from diffcontact.train.datamodule import ContactDataModule
from diffcontact.train.identify import refine
from diffcontact.train.module import KEEP_FAILED, ContactLightningModule, quiet_lightning, saved_config
from diffcontact.train.summary import against_nominal, learned_summary


def loss_curves(csv_dir: Path) -> dict[str, dict[int, float]]:
    """Train and validation loss by epoch ({"train/loss": {epoch: loss}, "val/loss": ...}) from the CSV logs under
    ``csv_dir``: every session of a resumed run, the newer log winning an epoch logged twice."""
    import csv

    curves: dict[str, dict[int, float]] = {"train/loss": {}, "val/loss": {}}
    for log in sorted(csv_dir.rglob("metrics.csv"), key=lambda p: p.stat().st_mtime):
        with log.open() as fh:
            for row in csv.DictReader(fh):
                for key, curve in curves.items():
                    if row.get(key):
                        curve[int(row["epoch"])] = float(row[key])
    return {key: dict(sorted(curve.items())) for key, curve in curves.items()}


def plot_losses(csv_dir: Path, out: Path) -> Path | None:
    """The loss curves (``loss_curves``) into a PNG; None if there is no log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = loss_curves(csv_dir)
    if not any(curves.values()):
        return None
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for key, curve in curves.items():
        if curve:
            ax.plot(list(curve), list(curve.values()), label=key)
    ax.set_xlabel("epoch")
    ax.set_ylabel("L1 loss")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    plt.close(fig)
    return out


def planned_epochs(epochs: int, min_steps: int, batches_per_epoch: int) -> int:
    """The epochs a run trains: ``epochs``, or more where that many epochs of ``batches_per_epoch`` optimiser steps
    fall short of ``min_steps`` (a small dataset: 8 real tosses make one batch an epoch).  The learning-rate
    schedule runs over these epochs."""
    return max(epochs, -(-min_steps // max(batches_per_epoch, 1)))


class _RunCheckpoint(ModelCheckpoint):
    """ModelCheckpoint whose record of the best and last checkpoints follows its run directory when the run was
    moved or copied (Lightning's would forget the best score and write last-v1.ckpt), and that writes last.ckpt at
    the end of every epoch: Lightning (2.6) writes it only when a best checkpoint is written in the same step, so a
    run whose validation loss had stopped improving resumed from its best epoch, not its last."""

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_end(trainer, pl_module)
        if self._should_save_on_train_epoch_end(trainer):
            self._save_last_too(trainer)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_validation_end(trainer, pl_module)
        if not self._should_save_on_train_epoch_end(trainer):
            self._save_last_too(trainer)

    def _save_last_too(self, trainer: pl.Trainer) -> None:
        """last.ckpt, where Lightning's save of this step (the hook above, just run) did not write it."""
        if self.save_last and not self._should_skip_saving_checkpoint(trainer):  # (skipped: written this step)
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    @property
    def state_key(self) -> str:  # (Lightning's own name: the checkpoints of runs made before keep their state)
        return "ModelCheckpoint" + super().state_key.removeprefix(type(self).__qualname__)

    def load_state_dict(self, state_dict: dict) -> None:
        old, new = state_dict.get("dirpath"), self.dirpath
        if old and old != new:
            if new is None:  # (never: _trainer gives the run's checkpoints folder)
                raise ValueError(f"cannot move the checkpoints of {old}: the checkpoint callback has no dirpath")

            def here(path):
                return str(Path(new) / Path(path).name) if path and Path(path).parent == Path(old) else path

            state_dict = dict(state_dict, dirpath=new)
            for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
                state_dict[key] = here(state_dict.get(key))
            state_dict["best_k_models"] = {here(k): v for k, v in state_dict.get("best_k_models", {}).items()}
        super().load_state_dict(state_dict)


class _AtomicCheckpointIO(TorchCheckpointIO):
    """Checkpoints written through ``files.atomic_write`` (a temporary file in the checkpoint folder, fsync,
    rename): a process killed while one is written leaves the previous one whole.  Lightning's own write goes
    through a temporary file in the system's temporary folder, moved by a copy when that is another file system,
    and leaves it behind when killed."""

    def save_checkpoint(self, checkpoint: dict, path, storage_options=None) -> None:
        atomic_write(Path(path), lambda fh: torch.save(checkpoint, fh))


class _ShuffleState(pl.Callback):
    """Keeps the state of the training data loader's random generator (the batch order) in the checkpoints, so that
    a resumed run draws the batches an uninterrupted run would (the loader's generator restarts from the seed)."""

    def __init__(self) -> None:
        self.loaded: torch.Tensor | None = None

    @staticmethod
    def _generator(trainer: pl.Trainer) -> torch.Generator | None:
        return getattr(trainer.train_dataloader, "generator", None)

    def on_save_checkpoint(self, trainer: pl.Trainer, pl_module, checkpoint: dict) -> None:
        if (gen := self._generator(trainer)) is not None:
            checkpoint["shuffle_rng"] = gen.get_state()

    def on_load_checkpoint(self, trainer: pl.Trainer, pl_module, checkpoint: dict) -> None:
        self.loaded = checkpoint.get("shuffle_rng")  # (None in checkpoints written before it was kept)

    def on_train_start(self, trainer: pl.Trainer, pl_module) -> None:
        if self.loaded is not None and (gen := self._generator(trainer)) is not None:
            # (the first epoch's loader iterator was made before this hook and drew its base seed from the fresh
            # generator: draw it again, as the uninterrupted run did after saving, so that the order is the same)
            gen.set_state(self.loaded)
            torch.empty((), dtype=torch.int64).random_(generator=gen)


# On noisy data (a dataset that records observation noise) a run stops once its validation loss has not improved
# for this many validations: there the best checkpoint comes early (epoch 23–179, at the median 70, in the 21 noisy
# runs of docs/results.md), and a stop after 30 keeps it or one within 0.3 % of its loss in 20 of them, at 40 % of
# the epochs (docs/training.md, "When a run stops").  On clean data the loss improves to the last epochs of the
# schedule, and a run trains all its epochs; so does a run that learns its chunks' first states (below), whose
# validation loss is least over their first states: BP5-e at noise 0.05 had its best checkpoint at epoch 133 of 200,
# where the stop ended the run at 95 with the checkpoint of epoch 64 (e 0.898 against 0.936, 5-step error 0.101
# against 0.059).
NOISY_PATIENCE = 30
# A run that learns its chunks' first states in a System's noise coordinates (the chain pendulum) keeps its last
# epoch as its best checkpoint: there the validation loss (least over the validation chunks' first states) was least
# early, while μ and e went on to the truth (noise 0.05, CP3: the checkpoint of epoch 31 had μ 0.445, e 0.034 and a
# 5-step error of 0.072, the last μ 0.476, e 0.000 and 0.046; CP3-e e 0.988 and 0.992, 0.036 and 0.039).  On free
# points the validation loss chooses (the Rope at noise 0.01: 0.155 at epoch 216, 0.667 at the last; BP5-e at 0.05
# 0.061 and 0.064; docs/training.md, "Noisy data").


def keeps_last_epoch(config: TrainConfig, system: System) -> bool:
    """Whether a run of ``config`` on ``system`` keeps its last epoch as its best checkpoint (see above)."""
    return bool(config.first_state_chunks) and system.noise_coordinates is not None


# On such data the first state of every training chunk is learned with the model (a contact model, the noise in
# coordinates a first state can be corrected in: ``first_state_settings``), at this fraction of the recorded noise
# a step.
FIRST_STATE_LR = 0.1
# ... and μ and e at the full learning rate (``coef_lr`` = 1; the default preset's 1/6 elsewhere), unless the command
# or the task file gives ``coef_lr``: on noisy chunks the gradient of e is small beside its noise from batch to batch,
# so Adam moves e about coef_lr × lr × (its mean over its spread) a step, and at 1/6 e crept toward the truth for the
# whole run and stopped short of it, where the loss, least over the first states, was still lower at the truth.  At
# noise 0.05 (seed 0; 1/6 against 1): CP3-e e 0.992 and 0.995, CP3 μ 0.476 and 0.489 (5-step errors 0.046 and
# 0.039), BP5-e e 0.933 and 0.934 (docs/training.md, "Noisy data").
NOISY_COEF_LR = 1.0
ACCELERATORS = ("cpu",)  # (the physics path keeps its constant tensors on the CPU: docs/scaling.md, GPUs)


def _resumed(run: RunDir, given: dict, epochs: int | None) -> tuple[TrainConfig, int]:
    """The recorded settings of the run in ``run``, with ``epochs`` where given, and the epochs it has trained:
    raises ConfigError if the run has no checkpoint or config, or if a ``given`` setting (not None) differs from the
    recorded one.  (Whether the epochs planned are fewer than those trained is known only with the data:
    ``min_steps``.)

    ``train_run(..., resume=True)`` continues from checkpoints/last.ckpt with these settings (``epochs`` may grow
    with a constant schedule); the result is the same as a run that was not interrupted, also after a SIGKILL at
    any moment (checkpoints are written atomically, ``_AtomicCheckpointIO``, the batch order is restored,
    ``_ShuffleState``; a run stopped before its first checkpoint starts again from its config)."""
    last = run.last_checkpoint
    if not last.is_file() and not run.config.is_file():
        raise ConfigError(f"--resume: no checkpoint to resume from at {last}")
    try:
        recorded = run.read_config()["args"]
        done, trained = 0, {}  # (a run stopped before its first checkpoint starts again)
        if last.is_file():
            checkpoint = torch.load(last, map_location="cpu", weights_only=False)
            done = int(checkpoint["epoch"]) + 1
            saved = saved_config(checkpoint)
            trained = {k: getattr(saved, k) for k in ("task", "model")}
    except (ConfigError, OSError, ValueError, KeyError, TypeError, RuntimeError, EOFError) as err:
        raise ConfigError(
            f"--resume: {run.path} is not a readable training run ({run.config.name}, {last.name}): {err}"
        ) from err
    config = TrainConfig.from_record(recorded, run.config)
    for key, value in trained.items():
        if value != getattr(config, key):
            raise ConfigError(f"--resume: {last} is of {key} {value!r}, config.json records {getattr(config, key)!r}")
    for key, value in given.items():
        if value is None:
            continue
        same = value == getattr(config, key)
        if key == "data_root":  # (the same folder, however written)
            value, same = str(value), Path(value).resolve() == Path(config.data_root).resolve()
        if not same:
            raise ConfigError(
                f"--resume: {key} = {value!r} differs from the run's {getattr(config, key)!r} ({run.config}); "
                "leave it out to continue the run as it was, or train into another --out"
            )
    epochs = config.epochs if epochs is None else epochs
    if epochs != config.epochs and config.schedule != "constant":
        raise ConfigError(
            f"--resume: epochs = {epochs} differs from the run's {config.epochs}, over which its "
            f"{config.schedule} learning rate schedule is planned (only a constant one can be extended)"
        )
    return config.replace(epochs=epochs), done


def _rank(devices: int) -> int:
    """The global rank of this process in a multi-process run (0 if there is none): torchrun's RANK, or from
    Lightning's launcher the node's rank and the local one."""
    if "RANK" in os.environ:
        return int(os.environ["RANK"])
    return int(os.environ.get("NODE_RANK", 0)) * devices + int(os.environ.get("LOCAL_RANK", 0))


def train_run(
    task: str | Path,
    model: str | None = None,
    *,
    out: str | Path | None = None,
    resume: bool = False,
    progress: bool = True,
    accelerator: str = "cpu",
    **settings,
) -> dict:
    """Train ``model`` (default CM-CD-CLNN) on the generated dataset of ``task`` (a packaged task's name or a task
    file's path) into the run directory ``out`` (default runs/<task>/<model>/seed<seed>; its files:
    :mod:`diffcontact.run_dir`), or with ``resume`` continue the run there (:func:`_resumed`).

    ``settings`` are those of :class:`~diffcontact.train.config.TrainConfig` (``seed``, ``epochs``, ``lr``,
    ``data_root``, ``devices`` ...: each documented there, their defaults by the preset, ``train.config.PRESETS``,
    and the task file's ``[training]`` table: :meth:`TrainConfig.resolve`); a setting given None is not given; an
    unknown one is a ConfigError.  ``devices`` × ``num_nodes`` processes train with DDP on ``accelerator`` ("cpu",
    the only one so far: :func:`_trainer`).  ``progress``: Lightning's progress bar.

    Returns the learned summary (on the other processes of a DDP run: the same, not written).
    """
    check_given(settings)
    _check_launch(accelerator, settings.get("devices"), settings.get("num_nodes"))
    quiet_lightning()
    parsed = load_task(task)  # (the task file, parsed once for the whole run)
    seed = 0 if settings.get("seed") is None else settings["seed"]
    run = RunDir(out) if out else RunDir.default(parsed.name, model or "CM-CD-CLNN", seed)
    first = _rank(settings.get("devices") or 1) == 0  # (the process that writes: the only one before a DDP launch)
    with output_lock(run.path) if first else nullcontext():  # (one command at a time writes a run)
        config, done = _settings(run, parsed, model, settings, resume)
        data = _data(config, parsed)
        if not done:  # (a new run: its first states learned or not, from what the dataset records)
            coef_given = settings.get("coef_lr") is not None or "coef_lr" in task_training(parsed)
            config = config.replace(**first_state_settings(config, data, coef_given))
        max_epochs = _planned(config, data, done)
        _record(run, config, accelerator, first)
        started = time.perf_counter()
        pl.seed_everything(config.seed, workers=True)
        module = ContactLightningModule(config, built_task=build_task(parsed))
        start = run.last_checkpoint if resume and run.last_checkpoint.is_file() else None
        patience = stop_patience(data.folder, config)
        last = keeps_last_epoch(config, module.task.system)
        trainer, checkpoints = _trainer(run, config, max_epochs, start, progress, accelerator, first, patience, last)
        if start is None and config.coef_start == "scan" and config.model in MODEL_NAMES:
            _scan_start(module, data, config, run, first)
        trainer.fit(module, datamodule=data, ckpt_path=str(start) if start else None)
        summary, failed = _finished(run, module, trainer, checkpoints.best_model_path, data, config.processes)
        summary["wall_time_s"] = module.seconds_before + time.perf_counter() - started  # (over all sessions)
        if patience:
            stopped = summary["epochs_trained"] < max_epochs
            summary["early_stop"] = {"patience": patience, "stopped": stopped, "planned_epochs": max_epochs}
        summary["run_dir"] = str(run.path)
        if trainer.is_global_zero:
            _write_finished(run, summary, failed)
        return summary


def _planned(config: TrainConfig, data: ContactDataModule, done: int) -> int:
    """The epochs the run plans (``planned_epochs``); ConfigError if fewer than the ``done`` it has trained."""
    max_epochs = planned_epochs(config.epochs, config.min_steps, data.batches_per_epoch(config.processes))
    if max_epochs < done:
        raise ConfigError(
            f"--resume: epochs = {config.epochs} (planned: {max_epochs}) is fewer than the {done} epochs the run "
            "has trained"
        )
    return max_epochs


def _write_finished(run: RunDir, summary: dict, failed: list[dict]) -> None:
    """The files of a finished training (the first process): solver_failures.npz (``_save_failed``, named in the
    summary), learned.json (the summary: written last of the run's records) and loss.png (``plot_losses``)."""
    if _save_failed(run, failed):
        summary["solver_failures_saved"] = run.solver_failures.name
    write_json(run.learned, summary)
    plot_losses(run.csv_logs, run.loss_figure)


def _save_failed(run: RunDir, problems: list[dict]) -> bool:
    """Add this session's failed contact problems (``ContactSolver.failed``: this process's first ones) to the
    run's ``solver_failures.npz`` (a resumed run's earlier ones kept first), at most ``KEEP_FAILED`` in all; a problem
    already in it (the same arrays: ``summarize`` run again on the same checkpoint meets the same ones) is not added
    again.  Returns whether the file exists."""
    path = run.solver_failures
    before = load_failed(path) if problems and path.is_file() else []
    seen, new = {_problem_key(p) for p in before}, []
    for problem in problems:
        if (key := _problem_key(problem)) not in seen:
            seen.add(key)
            new.append(problem)
    if new:
        save_failed(path, (before + new)[: max(KEEP_FAILED, len(before))])
    return path.is_file()


def _problem_key(problem: dict) -> tuple:
    """A failed problem's arrays (``ContactSolver.failed``), hashable: equal for the same problem met again."""
    return tuple(sorted((k, np.asarray(v).shape, np.asarray(v).tobytes()) for k, v in problem.items()))


def _check_launch(accelerator: str, devices: int | None, num_nodes: int | None) -> None:
    """ConfigError for an accelerator other than the CPU, or process counts that are not integers >= 1."""
    if accelerator not in ACCELERATORS:
        raise ConfigError(
            f"accelerator = {accelerator!r} is not one of {list(ACCELERATORS)}: the systems and the contact model keep "
            "their constant tensors on the CPU, and no run on a GPU has been made"
        )
    for key, value in (("devices", devices), ("num_nodes", num_nodes)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ConfigError(f"{key} = {value!r} is not an integer >= 1")


def _data(config: TrainConfig, task: TaskConfig | None = None) -> ContactDataModule:
    """The run's dataset: 5-frame chunks, or one-step pairs for the baselines (``task``: ``config.task`` parsed)."""
    return ContactDataModule(
        config.task if task is None else task,
        root=config.data_root,
        batch_size=config.batch_size,
        mode="pairs" if config.model in BASELINE_NAMES else "chunks",
        dtype=getattr(torch, config.dtype),
        seed=config.seed,
    )


def _finished(run: RunDir, module, trainer: pl.Trainer, best: str, data, processes: int) -> tuple[dict, list[dict]]:
    """The summary of a fitted run: what its best checkpoint learned (``_summary``), the checkpoint and the
    counters summed over the processes (``ContactLightningModule.totals``; every process calls this, only the first
    writes the files) and those of its refinement and identification (``solver_failures_after_training``), and
    the failed contact problems kept: training's, then those after it."""
    totals = module.totals()
    if trainer.world_size > 1:
        best = trainer.strategy.broadcast(best)  # (rank 0's choice: the one that wrote the checkpoints)
    # (the best checkpoint is in this run's folder, also when the folder was moved: _RunCheckpoint)
    built = build_task(data.config) if best else None  # (afresh, from the task file as the run parsed it)
    chosen = ContactLightningModule.from_checkpoint(best, built) if best else module
    failed_before = Counter(chosen.solver.failures_by_status)
    split, noise = data.splits["train"], recorded_noise(data.folder)
    train = chosen.as_fitted("train", split.chunk_x, split.chunk_v)
    val, write = data.splits["val"], trainer.is_global_zero
    refined, best = _refined(chosen, train, val, best, run.checkpoints, noise, write=write)
    calibrated, best = _calibrated(chosen, data.folder, best, run.checkpoints, write=write)
    summary = _summary(chosen, train, data, run) | {"best_checkpoint": best} | _counters(trainer, totals, processes)
    summary["solver_failures_after_training"] = dict(Counter(chosen.solver.failures_by_status) - failed_before)
    failed = module.solver.failed + (chosen.solver.failed if chosen is not module else [])
    summary |= {"refinement": refined} if refined else {}
    return summary | ({"calibration": calibrated} if calibrated else {}), failed


def _refined(
    chosen: ContactLightningModule, train, val, best: str, folder: Path, noise: float, write: bool
) -> tuple[dict, str]:
    """The chosen checkpoint's μ and e refined by Gauss–Newton on the training chunks ``train`` (chunk_x, chunk_v,
    as fitted: ``ContactLightningModule.as_fitted``), recorded with observation noise ``noise``
    (``identify.refine``), kept if the loss on the ``val`` split's chunks does not rise, and saved as
    ``folder``/refined-NAME (``write``: this process writes it).  Returns the refinement's record ({} for a model
    without learned contacts) and the checkpoint to use."""
    learned = chosen.learned
    if not chosen.learns_contacts or not best or learned is None:
        return {}, best
    chosen.eval()

    def val_loss() -> float:
        with torch.no_grad():
            return float(chosen.loss(chosen.as_fitted("val", val.chunk_x, val.chunk_v)))

    started, before = time.perf_counter(), val_loss()
    record = refine(chosen.net, *train, noise=noise)
    after = val_loss() if record["iterations"] else before
    record |= {"val_loss_before": before, "val_loss_after": after}
    if not after <= before:  # (worse on the validation split: the checkpoint as trained)
        with torch.no_grad():
            learned.mu_raw.copy_(torch.tensor(record["mu_before"]))
            learned.e_raw.copy_(torch.tensor(record["e_before"]))
        return record | {"kept": False, "seconds": time.perf_counter() - started}, best
    record |= {"kept": True, "seconds": time.perf_counter() - started}
    if not record["iterations"]:
        return record, best
    return record, _save_coefficients(best, learned, folder, write, REFINED_PREFIX)


def _calibrated(chosen: ContactLightningModule, data: Path, best: str, folder: Path, write: bool) -> tuple[dict, str]:
    """The chosen checkpoint's μ calibrated on the whole tosses of a measured dataset ``data``
    (``calibrate.calibrate_mu``) and, where kept, saved as ``_save_coefficients`` does.  Returns the calibration's
    record ({} for a dataset that is not measured or a model without a learned, projected μ) and the checkpoint."""
    learned = chosen.learned
    if not measured(data) or not chosen.learns_contacts or not best or learned is None:
        return {}, best
    if learned.mu_transform != "projected":  # (μ is not its raw parameter: the factor would not scale it)
        return {}, best
    record = calibrate_mu(chosen.net, learned.mu_raw, data)
    return record, _save_coefficients(best, learned, folder, write, CALIBRATED_PREFIX) if record["kept"] else best


def _save_coefficients(best: str, learned, folder: Path, write: bool, prefix: str) -> str:
    """The checkpoint ``best`` with the μ and e of ``learned`` (LearnedParams) in place of its own, saved as
    ``folder``/PREFIX-NAME (``write``: this process writes it).  Returns its path."""
    path = folder / f"{prefix}{Path(best).name}"
    if write:
        checkpoint = torch.load(best, map_location="cpu", weights_only=False)
        for key in ("mu_raw", "e_raw"):
            checkpoint["state_dict"][f"net.params.{key}"] = getattr(learned, key).detach().clone()
        atomic_write(path, lambda fh: torch.save(checkpoint, fh))
    return str(path)


def _settings(
    run: RunDir, task: TaskConfig, model: str | None, settings: dict, resume: bool
) -> tuple[TrainConfig, int]:
    """The run's settings and the epochs it has trained: a new run's, resolved from ``task`` (parsed) and the
    ``settings`` given (``TrainConfig.resolve``; refused beside another run's checkpoints), or with ``resume`` a
    resumed run's, as recorded (``_resumed``)."""
    given = dict(settings)
    preset, epochs = given.pop("preset", None), given.pop("epochs", None)
    if resume:
        return _resumed(run, dict(task=task.ref, model=model, preset=preset, **given), epochs)
    if run.checkpoints.is_dir() and any(run.checkpoints.glob("*.ckpt")):
        raise ConfigError(
            f"{run.checkpoints} already holds the checkpoints of a run: continue it with --resume, or train into "
            "another --out (or delete that run)"
        )
    return TrainConfig.resolve(task, model, preset, epochs=epochs, **given), 0


def _record(run: RunDir, config: TrainConfig, accelerator: str, first: bool) -> None:
    """Write config.json (the settings, the versions and how the processes share the work) and say it."""
    processes = config.processes
    parallel = dict(
        processes=processes,
        accelerator=accelerator,
        strategy="ddp" if processes > 1 else "single process",
        batch_per_process=config.batch_size,
        effective_batch=config.batch_size * processes,
        lr=config.lr,
        lr_scaling="none (the learning rate is not scaled with the effective batch)",
    )
    if first:
        run.path.mkdir(parents=True, exist_ok=True)
        record = {"args": config.record(), "versions": versions(lightning=lightning.__version__), "parallel": parallel}
        write_json(run.config, record)
    rank_zero_info(
        f"training on {processes} process(es) ({config.devices} device(s) x {config.num_nodes} node(s), "
        f"{accelerator}): batch {config.batch_size} per process, effective batch {parallel['effective_batch']}, "
        f"learning rate {config.lr:g} (not scaled)"
    )


def stop_patience(folder: str | Path, config: TrainConfig) -> int | None:
    """Validations without a better validation loss after which a run of ``config`` on the dataset in ``folder``
    stops: ``NOISY_PATIENCE`` where the dataset records observation noise and the run does not learn its chunks'
    first states, else None (all the planned epochs)."""
    return NOISY_PATIENCE if recorded_noise(folder) and not config.first_state_chunks else None


def recorded_noise(folder: str | Path) -> float:
    """The standard deviation of the observation noise the dataset in ``folder`` records (0: none)."""
    return float(load_meta(folder)["request"].get("noise") or 0.0)


def first_state_settings(config: TrainConfig, data: ContactDataModule, coef_given: bool = False) -> dict:
    """``first_state_chunks`` and ``first_state_lr`` of a run of ``config`` on ``data``: every training chunk's
    first state learned, at ``FIRST_STATE_LR`` × the noise a step, where the dataset records observation noise, the
    model is a contact model and the noise is i.i.d. in coordinates the first states can be corrected in (the free
    points' Cartesian ones: balls, the rope; a System's ``noise_coordinates``: the chain pendulum's link angles);
    none otherwise (noise projected onto the constraints: the disks, the gyroscope; docs/training.md, "Noisy
    data").  Such a run also learns μ and e at ``NOISY_COEF_LR`` (``coef_lr``) unless ``coef_given`` (the command
    or the task file gives it)."""
    noise = recorded_noise(data.folder)
    projected = noise_kind(build_task(data.config).system) == "projected"  # (the task as parsed by ``data``)
    if not noise * FIRST_STATE_LR or config.model not in MODEL_NAMES or projected:
        return {"first_state_chunks": 0, "first_state_val_chunks": 0, "first_state_lr": 0.0}
    data.setup()
    train, val = (len(data.splits[name].chunk_x) for name in ("train", "val"))
    settings = {"first_state_chunks": train, "first_state_val_chunks": val, "first_state_lr": FIRST_STATE_LR * noise}
    return settings if coef_given else settings | {"coef_lr": NOISY_COEF_LR}


def _trainer(
    run: RunDir,
    config: TrainConfig,
    max_epochs: int,
    start: Path | None,
    progress: bool,
    accelerator: str,
    first: bool,
    patience: int | None = None,
    keep_last: bool = False,
) -> tuple[pl.Trainer, _RunCheckpoint]:
    """The run's Lightning trainer (logs, atomic checkpoints every epoch, the best on val/loss, a stop after
    ``patience`` validations without a better val/loss if given) and its checkpoint callback.

    ``config.devices`` processes on each of ``config.num_nodes`` machines (default 1 and 1) train with Lightning's
    DDP strategy (gloo between CPU processes; ``accelerator`` "cpu", the only one so far): ``batch_size`` is the
    batch of each process, the effective batch is batch_size × devices × num_nodes, and the learning rate is not
    scaled with it (all three are logged and recorded in config.json: ``_record``).  Only the first process
    (``first``) writes the files.  docs/scaling.md."""
    loggers = [CSVLogger(run.logs, name=run.csv_logs.name), TensorBoardLogger(run.logs, name=run.tb_logs.name)]
    monitor, mode = ("epoch", "max") if keep_last else ("val/loss", "min")  # (``keeps_last_epoch``)
    checkpoints = _RunCheckpoint(
        dirpath=run.checkpoints,
        filename=BEST_CHECKPOINT,
        monitor=monitor,
        mode=mode,
        save_top_k=1,
        save_last=True,
        every_n_epochs=1,
        enable_version_counter=False,  # (one last.ckpt, always the newest)
    )
    for tmp in run.checkpoints.glob(f"{TMP_PREFIX}*") if first else ():  # (a checkpoint half-written at a kill)
        tmp.unlink(missing_ok=True)
    processes = config.processes
    trainer = pl.Trainer(
        max_epochs=max_epochs,
        # (epochs raised for a small dataset validate as often as the epochs asked for would: the validation
        # split is not smaller, and validating it every epoch of 8 tosses cost 5 times the training)
        check_val_every_n_epoch=max(1, max_epochs // config.epochs),
        plugins=[_AtomicCheckpointIO()],
        logger=loggers,
        callbacks=[checkpoints, _ShuffleState()]
        + ([EarlyStopping(monitor="val/loss", mode="min", patience=patience)] if patience else []),
        enable_progress_bar=progress,
        deterministic=True,
        log_every_n_steps=1,
        enable_model_summary=False,
        num_sanity_val_steps=0 if start else 2,  # (as the uninterrupted run: its counters include it once)
        inference_mode=False,  # (no_grad: a validation step may move its chunks' learned first states)
        accelerator=accelerator,
        devices=config.devices,
        num_nodes=config.num_nodes,
        strategy=DDPStrategy(find_unused_parameters=True) if processes > 1 else "auto",
    )
    return trainer, checkpoints


def _scan_start(module: ContactLightningModule, data: ContactDataModule, config: TrainConfig, run: RunDir, first):
    """Start μ and e from the least training loss of a scan (train/coef_start.py), recorded in coef_start.json."""
    data.setup()
    train = data.splits["train"]
    record = scan_coefficients(module, train.chunk_x, train.chunk_v, config.seed)
    rank_zero_info(f"μ and e start at {record['chosen']} (the least loss of a scan)")
    if first:
        write_json(run.coef_start, record)


def _summary(
    chosen: ContactLightningModule, train: tuple[torch.Tensor, torch.Tensor], data: ContactDataModule, run: RunDir
) -> dict:
    """What the checkpoint chosen on the validation split learned, and what the training data can identify; a
    measured dataset's table height; where μ and e started."""
    summary = learned_summary(chosen.net, chosen.task, *train, recorded_noise(data.folder))
    request = load_meta(data.folder)["request"]
    if request.get("measured"):  # (the task's values are nominal; the table's height is the importer's estimate)
        summary = against_nominal(summary)
        summary["table_height_m"] = {"value": request["table_height_m"], "how": request["table_height_method"]}
    if run.coef_start.is_file():
        summary["coef_start"] = json.loads(run.coef_start.read_text())["chosen"]
    return summary


def _counters(trainer: pl.Trainer, totals: dict, processes: int) -> dict:
    """The run's epochs, steps and failure counters (summed over its processes), and who wrote the files."""
    counters = {"epochs_trained": int(trainer.current_epoch), "optimiser_steps": int(trainer.global_step)}
    return counters | totals | {"processes": processes, "rank": trainer.global_rank}  # (rank 0 wrote the files)


def summarize_run(run: str | Path) -> dict:
    """Recompute the learned-against-true part of ``run``/learned.json from its best checkpoint and training data
    (after an upgrade of the summary), refining μ and e first if the run predates the refinement; the run's
    counters and times are kept.  Returns the new summary."""
    from diffcontact.data.store import dataset_folder, load_split

    run_dir = RunDir(run)
    old, args = run_dir.read_learned(), run_dir.read_config()["args"]
    best = run_dir.best_checkpoint()  # (in the run's own folder if it was moved)
    chosen = ContactLightningModule.from_checkpoint(best)
    config = chosen.task.config
    dtype, folder = getattr(torch, args.get("dtype", "float32")), dataset_folder(args["data_root"], config.name)
    train_split, val = (load_split(folder, name, config, dtype=dtype) for name in ("train", "val"))
    train = chosen.as_fitted("train", train_split.chunk_x, train_split.chunk_v)
    refined, calibrated, failed_before = {}, {}, Counter(chosen.solver.failures_by_status)
    current = str(best)
    if "refinement" not in old:  # (a run trained before the refinement: refined now, as training does)
        refined, current = _refined(chosen, train, val, current, run_dir.checkpoints, recorded_noise(folder), True)
    if "calibration" not in old:  # (a run trained before the calibration: calibrated now, as training does)
        calibrated, current = _calibrated(chosen, folder, current, run_dir.checkpoints, write=True)
    if current != str(best):
        old["best_checkpoint"] = current
    fresh = learned_summary(chosen.net, chosen.task, *train, recorded_noise(folder))
    if load_meta(folder)["request"].get("measured"):
        fresh = against_nominal(fresh)
    kept = {k: v for k, v in old.items() if k not in fresh and not k.startswith("collisions")}
    summary = {**fresh, **kept} | ({"refinement": refined} if refined else {})
    summary |= {"calibration": calibrated} if calibrated else {}
    summary["solver_failures_after_training"] = dict(Counter(chosen.solver.failures_by_status) - failed_before)
    if _save_failed(run_dir, chosen.solver.failed):
        summary["solver_failures_saved"] = run_dir.solver_failures.name
    write_json(run_dir.learned, summary)
    return summary
