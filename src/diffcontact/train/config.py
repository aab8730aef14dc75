"""One definition of a training run's settings: :class:`TrainConfig`.

A run's settings come from three places, in this order: a preset (``PRESETS``: "default", what learns on every task
measured, docs/investigations.md; "published", the paper's), the task file's ``[training]`` table (with the
default preset only: :func:`task_training`) and what the caller gives.  :meth:`TrainConfig.resolve` applies them and
validates every setting once; the run writes the result into config.json (``"args"``), a resumed run reads it back
(:meth:`TrainConfig.from_record`), and the Lightning module takes it as its one settings argument.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from diffcontact.config import TaskConfig, load_task
from diffcontact.errors import ConfigError
from diffcontact.models import ALL_MODELS, BASELINE_NAMES, MODEL_NAMES
from diffcontact.models.params import E_TRANSFORMS, MU_TRANSFORMS, POTENTIALS
from diffcontact.run_dir import CONFIG

SCHEDULES = ("constant", "cosine")  # of the learning rate over the epochs
TRAIN_LOSSES = ("l1", "mse")  # the training loss, and val/loss's (which chooses the checkpoint)
COEF_STARTS = ("random", "scan")  # where μ and e start: train/coef_start.py
DTYPES = ("float32", "float64")


@dataclass(frozen=True)
class TrainConfig:
    """Every setting of a training run, validated on construction (ConfigError naming the field and what is allowed).

    The defaults are the default preset's.  ``task``: a packaged task's name or a task file's path; ``reg``: a CMr
    model's regularisation (None: the model's own; the exact models and the baselines have none); ``task_training``:
    the task file's ``[training]`` table that was applied; ``devices`` × ``num_nodes`` processes (DDP).
    """

    task: str
    model: str = "CM-CD-CLNN"
    preset: str = "default"
    seed: int = 0
    epochs: int = 200
    batch_size: int = 50
    lr: float = 1e-2
    schedule: str = "cosine"
    weight_decay: float = 1e-4
    mu_transform: str = "projected"
    e_transform: str = "projected"
    coef_lr: float = 1 / 6  # μ and e at coef_lr × lr (Adam moves a parameter about lr a step, whatever its gradient)
    mu_coef_lr: float | None = None  # (μ's own, where given)
    mu_l1: float = 0.0  # a constant pull of every μ toward 0
    reg: float | None = None
    train_loss: str = "l1"  # "l1" (the paper's) or "mse" (a deviation measured for the baselines, docs/baselines.md)
    potential: str = "mlp"  # "mlp" (the paper's learned network), "linked" (plus one per link), "gravity" or "known"
    velocity_weight: float = 1.0  # of the velocities in the loss, against the positions
    moments_init: float = 1.0  # m² per unit mass: where the learned second moments start (about the bodies' size²)
    axis_scale: float = 1.0  # m: the weight in the loss of an extended body's axis points against its centre
    min_steps: int = 0  # the fewest optimiser steps: a small dataset's epochs are raised to reach them
    coef_start: str = "random"
    hidden: int = 256  # the learned networks' width and depth (the paper's 256 × 3)
    layers: int = 3
    dtype: str = "float32"
    # the training and validation chunks whose first states are learned with the model (0: none), and the largest
    # move of one in a step, in m (or m/s): set from the dataset's recorded noise (``train.run.first_state_settings``)
    first_state_chunks: int = 0
    first_state_val_chunks: int = 0
    first_state_lr: float = 0.0
    data_root: str = "data"
    task_training: dict = field(default_factory=dict)
    devices: int = 1
    num_nodes: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.task, str) or not self.task:
            raise ConfigError(f"task = {self.task!r} is not a task's name or a task file's path")
        _one_of("model", self.model, ALL_MODELS)
        _one_of("preset", self.preset, PRESETS)
        _one_of("schedule", self.schedule, SCHEDULES)
        _one_of("train_loss", self.train_loss, TRAIN_LOSSES)
        _one_of("mu_transform", self.mu_transform, MU_TRANSFORMS)
        _one_of("e_transform", self.e_transform, E_TRANSFORMS)
        _one_of("potential", self.potential, POTENTIALS)
        _one_of("coef_start", self.coef_start, COEF_STARTS)
        _one_of("dtype", self.dtype, DTYPES)
        for key in ("seed", "min_steps", "first_state_chunks", "first_state_val_chunks"):
            _integer(key, getattr(self, key), 0)
        for key in ("epochs", "batch_size", "hidden", "layers", "devices", "num_nodes"):
            _integer(key, getattr(self, key), 1)
        for key in ("lr", "coef_lr", "moments_init", "axis_scale"):
            _number(key, getattr(self, key), positive=True)
        for key in ("weight_decay", "mu_l1", "velocity_weight", "first_state_lr"):
            _number(key, getattr(self, key), positive=False)
        if self.mu_coef_lr is not None:
            _number("mu_coef_lr", self.mu_coef_lr, positive=True)
        if self.reg is not None:  # (recorded: 0 for the exact models, the regularisation for CMr, None otherwise)
            _number("reg", self.reg, positive=False)
            regularised = self.model in MODEL_NAMES and MODEL_NAMES[self.model][1] > 0
            if self.reg > 0 and not regularised or self.model in BASELINE_NAMES:
                raise ConfigError(f"reg = {self.reg:g} is for the regularised models (CMr-...), not {self.model}")
            if regularised and self.reg == 0:
                raise ConfigError(f"reg = 0 is not > 0 for {self.model} (the exact model is CM-...)")
        if self.first_state_chunks and self.devices * self.num_nodes > 1:
            raise ConfigError(
                f"devices × num_nodes = {self.devices * self.num_nodes}: a run that learns its chunks' first states "
                "(data recorded with observation noise) trains on one process"
            )
        if not isinstance(self.data_root, str) or not isinstance(self.task_training, dict):
            raise ConfigError(f"data_root = {self.data_root!r} must be a path and task_training a table")

    @classmethod
    def resolve(
        cls, task: str | Path | TaskConfig, model: str | None = None, preset: str | None = None, **given
    ) -> TrainConfig:
        """The settings of a new run of ``model`` (default CM-CD-CLNN) on ``task`` (its name, its file's path or
        the ``TaskConfig`` parsed from it): ``preset`` (default "default"), then the task file's ``[training]``
        table (default preset only), then ``given`` where not None."""
        model, preset = model or "CM-CD-CLNN", preset or "default"
        config = task if isinstance(task, TaskConfig) else load_task(task)  # (its reference, its [training] table)
        ref = config.ref  # (a packaged task's name, or a task file's path as found from anywhere)
        own = task_training(config) if preset == "default" else {}
        chosen = {k: given.pop(k) for k in PRESET_SETTINGS if k in given}
        settings = resolve_preset(preset, own, **chosen)
        if model in BASELINE_NAMES:
            # (a baseline's one-step pair weighs velocities as the paper's loss does, whatever the task's setting for
            # the contact models' windows: its velocity jump moves no position within its step, so without them it
            # would get no gradient at all)
            settings["velocity_weight"] = 1.0
        given = {k: str(v) if k == "data_root" else v for k, v in given.items() if v is not None}
        if model in MODEL_NAMES and given.get("reg") is None:
            given["reg"] = MODEL_NAMES[model][1]  # (a CMr model's default regularisation; None for the others)
        return cls._make(task=ref, model=model, preset=preset, task_training=own, **settings, **given)

    @classmethod
    def from_record(cls, args: dict, where: str | Path = CONFIG) -> TrainConfig:
        """The settings a run recorded (config.json ``"args"``).  Settings added since a run was made take the
        value such runs trained with (``LATER_SETTINGS``); any other missing one is a ConfigError."""
        missing = [f.name for f in dataclasses.fields(cls) if f.name not in args and f.name not in LATER_SETTINGS]
        if missing:
            raise ConfigError(f"{where} lacks {missing} (a run of an older version)")
        return cls._make(**{**LATER_SETTINGS, **args})

    @classmethod
    def _make(cls, **settings) -> TrainConfig:
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(settings) - set(known))
        if unknown:
            raise ConfigError(f"unknown training settings {unknown}; known: {known}")
        return cls(**settings)

    @property
    def processes(self) -> int:
        """The processes of the run: ``devices`` on each of ``num_nodes`` machines."""
        return self.devices * self.num_nodes

    def replace(self, **changes) -> TrainConfig:
        """A copy with ``changes``, validated."""
        return dataclasses.replace(self, **changes)

    def record(self) -> dict:
        """The settings as config.json records them (``"args"``)."""
        return dataclasses.asdict(self)


def _one_of(key: str, value, allowed) -> None:
    if value not in allowed:
        raise ConfigError(f"{key} = {value!r} is not one of {list(allowed)}")


def _integer(key: str, value, lo: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ConfigError(f"{key} = {value!r} is not an integer >= {lo}")


def _number(key: str, value, positive: bool) -> None:
    bad = isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0
    if bad or (positive and value == 0):
        raise ConfigError(f"{key} = {value!r} is not a finite number {'> 0' if positive else '>= 0'}")


# The settings a preset and a task file's [training] table set.
PRESET_SETTINGS = (
    "epochs", "lr", "schedule", "batch_size", "mu_transform", "e_transform", "coef_lr", "mu_coef_lr", "mu_l1",
    "potential", "velocity_weight", "moments_init", "axis_scale", "min_steps", "coef_start",
)  # fmt: skip
# Presets by name, as changes to TrainConfig's defaults (the default preset's).
PRESETS = {
    "default": {},
    "published": dict(
        epochs=1000,
        lr=1e-3,
        schedule="constant",
        batch_size=200,
        mu_transform="relu",
        e_transform="hardsigmoid",
        coef_lr=1.0,
    ),
}
# The settings a caller gives a run (``train.run.train_run``'s keyword arguments): all but the task and the model
# (given apart) and those the run derives from the task file and the dataset.
DERIVED = ("task", "model", "task_training", "first_state_chunks", "first_state_val_chunks", "first_state_lr")
GIVEN_SETTINGS = tuple(sorted(f.name for f in dataclasses.fields(TrainConfig) if f.name not in DERIVED))
# Settings added after runs were made, and the value those runs trained with (for resuming them).
LATER_SETTINGS = dict(
    train_loss="l1", devices=1, num_nodes=1, mu_l1=0.0, potential="mlp", velocity_weight=1.0, moments_init=1.0,
    axis_scale=1.0, min_steps=0, coef_start="random", hidden=256, layers=3, task_training={}, first_state_chunks=0,
    first_state_val_chunks=0, first_state_lr=0.0,
)  # fmt: skip


def check_given(settings: dict) -> None:
    """ConfigError naming the settings that are not ``GIVEN_SETTINGS`` (listed, sorted), if any."""
    unknown = sorted(set(settings) - set(GIVEN_SETTINGS))
    if unknown:
        raise ConfigError(f"unknown training settings {unknown}; allowed: {list(GIVEN_SETTINGS)}")


def resolve_preset(preset: str, task_settings: dict | None = None, **given) -> dict:
    """The ``PRESET_SETTINGS`` of ``preset``, then the task's own (``task_training``; default preset only), each
    replaced where given (not None)."""
    _one_of("preset", preset, PRESETS)
    unknown = set(given) - set(PRESET_SETTINGS)
    if unknown:
        raise ConfigError(f"unknown settings {sorted(unknown)}; known: {list(PRESET_SETTINGS)}")
    defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig) if f.name in PRESET_SETTINGS}
    base = {**defaults, **PRESETS[preset], **((task_settings or {}) if preset == "default" else {})}
    return {k: v if given.get(k) is None else given[k] for k, v in base.items()}


def task_training(task: str | Path | TaskConfig) -> dict:
    """The ``[training]`` table of a task file (or of its parsed ``TaskConfig``): the settings of the default preset
    that differ for this task (for example ``mu_coef_lr``), each checked against its domain."""
    table = (task if isinstance(task, TaskConfig) else load_task(task)).section("training")
    defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig)}
    settings = {}
    for key in table.data:
        if key not in PRESET_SETTINGS:
            raise ConfigError(f"training.{key} is not a training setting; known: {list(PRESET_SETTINGS)}")
        if isinstance(defaults[key], str):  # (its options are checked by TrainConfig)
            if not isinstance(table.get(key), str):
                raise ConfigError(f"training.{key} = {table.get(key)!r} is not a string")
            settings[key] = table.get(key)
        elif key in ("epochs", "batch_size", "min_steps"):
            settings[key] = table.integer(key, lo=0 if key == "min_steps" else 1)
        else:  # (rates > 0; a pull or a weight may be 0)
            settings[key] = table.number(key, lo=0.0, lo_open=key not in ("mu_l1", "velocity_weight"))
    return settings
