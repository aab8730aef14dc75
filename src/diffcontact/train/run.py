"""A training run: data, model, Lightning trainer, checkpoints, logs and the learned parameters."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import lightning.pytorch as pl
import torch

import diffcontact
from diffcontact.errors import ConfigError
from diffcontact.models import BASELINE_NAMES, MODEL_NAMES
from diffcontact.train.datamodule import ContactDataModule
from diffcontact.train.module import ContactLightningModule
from diffcontact.train.summary import learned_summary


def _write_json(path: Path, obj) -> None:
    """Write JSON to a temporary file, then rename (an interrupted run leaves no half-written file)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2) + "\n")
    os.replace(tmp, path)


def plot_losses(csv_dir: Path, out: Path) -> Path | None:
    """Train and validation loss per epoch from the CSV log (the newest version) into a PNG; None if no log."""
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    logs = sorted(csv_dir.rglob("metrics.csv"), key=lambda p: p.stat().st_mtime)
    if not logs:
        return None
    curves: dict[str, dict[int, float]] = {"train/loss": {}, "val/loss": {}}
    with logs[-1].open() as fh:
        for row in csv.DictReader(fh):
            for key, curve in curves.items():
                if row.get(key):
                    curve[int(row["epoch"])] = float(row[key])
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for key, curve in curves.items():
        if curve:
            ax.plot(list(curve), list(curve.values()), label=key)
    ax.set_xlabel("epoch")
    ax.set_ylabel("L1 loss")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    tmp = out.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, out)
    return out


# Training settings by name.  "default": what learns on every task measured (docs/results.md, the learning
# matrix); "published": the paper's (spec E), kept for comparison.
PRESETS = {
    "default": dict(
        epochs=200,
        lr=1e-2,
        schedule="cosine",
        batch_size=50,
        mu_transform="projected",
        e_transform="projected",
        coef_lr=1 / 6,
        mu_coef_lr=None,
    ),
    "published": dict(
        epochs=1000,
        lr=1e-3,
        schedule="constant",
        batch_size=200,
        mu_transform="relu",
        e_transform="hardsigmoid",
        coef_lr=1.0,
        mu_coef_lr=None,
    ),
}


def task_training(task: str | Path) -> dict:
    """The ``[training]`` table of a task file: the settings of the default preset that differ for this task
    (for example ``mu_coef_lr``), each checked against the preset's known settings and their domains."""
    from diffcontact.config import load_task

    table = load_task(task).section("training")
    known = PRESETS["default"]
    settings = {}
    for key in table.data:
        if key not in known:
            raise ConfigError(f"training.{key} is not a training setting; known: {list(known)}")
        if isinstance(known[key], str):  # (its options are checked where it is used)
            if not isinstance(table.get(key), str):
                raise ConfigError(f"training.{key} = {table.get(key)!r} is not a string")
            settings[key] = table.get(key)
        elif key in ("epochs", "batch_size"):
            settings[key] = table.integer(key, lo=1)
        else:
            settings[key] = table.number(key, lo=0.0, lo_open=True)
    return settings


def resolve_preset(preset: str, task_settings: dict | None = None, **given) -> dict:
    """The settings of ``preset`` (``PRESETS``), then the task's own (``task_training``; default preset only),
    each replaced where given (not None)."""
    if preset not in PRESETS:
        raise ConfigError(f"preset = {preset!r} is not one of {list(PRESETS)}")
    unknown = set(given) - set(PRESETS[preset])
    if unknown:
        raise ConfigError(f"unknown settings {sorted(unknown)}; known: {list(PRESETS[preset])}")
    base = {**PRESETS[preset], **(task_settings or {})} if preset == "default" else PRESETS[preset]
    return {k: v if given.get(k) is None else given[k] for k, v in base.items()}


def train_run(
    task: str,
    model: str = "CM-CD-CLNN",
    *,
    preset: str = "default",
    epochs: int | None = None,
    seed: int = 0,
    out: str | Path | None = None,
    data_root: str | Path = "data",
    batch_size: int | None = None,
    lr: float | None = None,
    schedule: str | None = None,
    weight_decay: float = 1e-4,
    mu_transform: str | None = None,
    e_transform: str | None = None,
    coef_lr: float | None = None,
    mu_coef_lr: float | None = None,
    reg: float | None = None,
    train_loss: str = "l1",
    dtype: str = "float32",
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Train ``model`` on the generated dataset of ``task`` into ``out`` (default runs/<task>/<model>/seed<seed>).

    ``preset`` names the training settings (``PRESETS``), which the task file's ``[training]`` table adjusts for
    the default preset; ``epochs``, ``lr``, ``schedule``, ``batch_size``, the transforms and the rates override
    them where given.
    ``train_loss`` ("l1", the paper's, or "mse", a deviation measured for the baselines in
    docs/baselines.md) is the training loss; val/loss, which selects the checkpoint, is always L1.

    The run directory holds config.json (arguments and versions), checkpoints/ (best on val/loss and last, every
    epoch), logs/ (CSV and TensorBoard), learned.json and loss.png (the loss curves).  ``resume`` continues
    from checkpoints/last.ckpt.
    Returns the learned summary.
    """
    if model not in MODEL_NAMES and model not in BASELINE_NAMES:
        raise ConfigError(f"model = {model!r} is not one of {list(MODEL_NAMES) + list(BASELINE_NAMES)}")
    own = task_training(task)
    settings = resolve_preset(
        preset,
        own,
        epochs=epochs,
        lr=lr,
        schedule=schedule,
        batch_size=batch_size,
        mu_transform=mu_transform,
        e_transform=e_transform,
        coef_lr=coef_lr,
        mu_coef_lr=mu_coef_lr,
    )
    coef_lr, mu_coef_lr = settings["coef_lr"], settings["mu_coef_lr"]
    epochs, lr, schedule, batch_size = (settings[k] for k in ("epochs", "lr", "schedule", "batch_size"))
    mu_transform, e_transform = settings["mu_transform"], settings["e_transform"]
    if epochs < 1:
        raise ConfigError(f"epochs = {epochs} is not >= 1")
    run = Path(out) if out else Path("runs") / task / model / f"seed{seed}"
    ckpt_dir = run / "checkpoints"
    last = ckpt_dir / "last.ckpt"
    if resume and not last.is_file():
        raise ConfigError(f"--resume: no checkpoint to resume from at {last}")
    run.mkdir(parents=True, exist_ok=True)
    args = dict(
        task=task,
        model=model,
        preset=preset,
        epochs=epochs,
        seed=seed,
        batch_size=batch_size,
        lr=lr,
        schedule=schedule,
        coef_lr=coef_lr,
        mu_coef_lr=mu_coef_lr,
        reg=MODEL_NAMES[model][1] if reg is None and model in MODEL_NAMES else reg,
        weight_decay=weight_decay,
        train_loss=train_loss,
        mu_transform=mu_transform,
        e_transform=e_transform,
        dtype=dtype,
        data_root=str(data_root),
        task_training=own if preset == "default" else {},  # (the task file's [training] table, applied above)
    )
    versions = dict(
        diffcontact=diffcontact.__version__,
        torch=torch.__version__,
        lightning=pl.__version__,
        python=platform.python_version(),
    )
    _write_json(run / "config.json", {"args": args, "versions": versions})

    started = time.perf_counter()
    pl.seed_everything(seed, workers=True)
    mode = "pairs" if model in BASELINE_NAMES else "chunks"  # (the baselines train on one-step pairs)
    data = ContactDataModule(
        task, root=data_root, batch_size=batch_size, mode=mode, dtype=getattr(torch, dtype), seed=seed
    )
    module = ContactLightningModule(
        task,
        model,
        lr=lr,
        weight_decay=weight_decay,
        mu_transform=mu_transform,
        e_transform=e_transform,
        seed=seed,
        dtype=dtype,
        schedule=schedule,
        coef_lr=coef_lr,
        mu_coef_lr=mu_coef_lr,
        reg=reg,
        train_loss=train_loss,
    )
    loggers = [pl.loggers.CSVLogger(run / "logs", name="csv"), pl.loggers.TensorBoardLogger(run / "logs", name="tb")]
    checkpoints = pl.callbacks.ModelCheckpoint(
        dirpath=ckpt_dir,
        filename="best-{epoch}",
        monitor="val/loss",
        mode="min",
        save_top_k=1,
        save_last=True,
        every_n_epochs=1,
    )
    trainer = pl.Trainer(
        max_epochs=epochs,
        logger=loggers,
        callbacks=[checkpoints],
        enable_progress_bar=progress,
        deterministic=True,
        log_every_n_steps=1,
        enable_model_summary=False,
    )
    trainer.fit(module, datamodule=data, ckpt_path=str(last) if resume else None)
    best = checkpoints.best_model_path
    chosen = ContactLightningModule.load_from_checkpoint(best, map_location="cpu") if best else module
    # the parameters of the checkpoint chosen on the validation split, and what the training data can identify
    train = data.splits["train"]
    summary = learned_summary(chosen.net, chosen.task, train.chunk_x, train.chunk_v)
    summary["best_checkpoint"] = best
    summary["epochs_trained"] = int(trainer.current_epoch)
    summary["skipped_steps"] = module.skipped_steps
    summary["solver_failures"] = module.solver_failures
    summary["solver_failures_by_status"] = dict(module.solver_failures_by_status)
    summary["wall_time_s"] = time.perf_counter() - started
    summary["run_dir"] = str(run)
    _write_json(run / "learned.json", summary)
    plot_losses(run / "logs" / "csv", run / "loss.png")
    return summary


def summarize_run(run: str | Path) -> dict:
    """Recompute the learned-against-true part of ``run``/learned.json from its best checkpoint and training data
    (after an upgrade of the summary); the run's counters and times are kept.  Returns the new summary."""
    from diffcontact.data.store import load_split

    run = Path(run)
    try:
        old = json.loads((run / "learned.json").read_text())
        args = json.loads((run / "config.json").read_text())["args"]
    except (OSError, ValueError, KeyError) as err:
        raise ConfigError(f"{run} is not a finished training run (learned.json, config.json): {err}") from err
    best = Path(old.get("best_checkpoint") or "")
    if not best.is_file():  # (a run directory that was moved: its own checkpoints folder)
        best = run / "checkpoints" / best.name
    if not best.is_file():
        raise ConfigError(f"{run}: the best checkpoint {old.get('best_checkpoint')!r} is missing")
    chosen = ContactLightningModule.load_from_checkpoint(best, map_location="cpu")
    train = load_split(Path(args["data_root"]) / args["task"], "train")
    fresh = learned_summary(chosen.net, chosen.task, train.chunk_x, train.chunk_v)
    kept = {k: v for k, v in old.items() if k not in fresh and not k.startswith("collisions")}
    summary = {**fresh, **kept}
    _write_json(run / "learned.json", summary)
    return summary
