"""Load a trained run for evaluation: its config, best checkpoint and model, through a registry of builders.

A run directory (:class:`diffcontact.run_dir.RunDir`) records its task and model in ``config.json`` and names its
best checkpoint in ``learned.json``.  The model is built by the
builder registered for the run's recorded model name; a builder returns an ``nn.Module`` with
``forward(x0, v0, frames) -> (xs, vs)``, x0, v0 (B, P, d) and xs, vs (B, frames, P, d) with frame 0 included.
Other models (the baselines) join by calling :func:`register_model`; evaluation never branches on the name.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from torch import nn

from diffcontact.errors import ConfigError
from diffcontact.run_dir import RunDir
from diffcontact.systems.base import Task

# builder(run_dir, config, checkpoint, task) -> the trained model
ModelBuilder = Callable[[Path, dict, Path, Task], nn.Module]
_BUILDERS: dict[str, ModelBuilder] = {}


def register_model(names: str | Iterable[str], builder: ModelBuilder) -> None:
    """Make the runs of model ``names`` loadable by ``builder(run_dir, config, checkpoint, task)``."""
    for name in [names] if isinstance(names, str) else names:
        _BUILDERS[name] = builder


def registered_models() -> list[str]:
    """The model names whose runs can be loaded."""
    return sorted(_BUILDERS)


@dataclass(frozen=True)
class LoadedRun:
    """A trained run: its directory, recorded config (``args`` and ``versions``), checkpoint, Task and model."""

    run_dir: Path
    config: dict
    checkpoint: Path
    task: Task
    net: nn.Module

    @property
    def task_name(self) -> str:
        """The task's name (its dataset's folder; ``args.task`` may be a task file's path)."""
        return self.task.config.name

    @property
    def model_name(self) -> str:
        return self.config["args"]["model"]


def load_run(run: str | Path, task: str | None = None) -> LoadedRun:
    """Load a run's best model through the builder registered for its model name.

    ``task``: the task the caller expects (a packaged task's name or a task file's path, compared by task name); a
    run of another task is a ConfigError, as are a missing config, an unregistered model, and a missing or
    unreadable checkpoint.
    """
    from diffcontact.config import load_task
    from diffcontact.systems.registry import build_task

    run = Path(run)
    config = RunDir(run).read_config()
    name, model = config["args"]["task"], config["args"]["model"]
    built = build_task(name)
    if task is not None and built.config.name != load_task(task).name:
        raise ConfigError(f"{run} is a run of task {built.config.name!r}, not {task!r}")
    builder = _BUILDERS.get(model)
    if builder is None:
        raise ConfigError(f"{run}: model {model!r} has no registered loader; known: {registered_models()}")
    checkpoint = RunDir(run).best_checkpoint()
    net = builder(run, config, checkpoint, built)
    return LoadedRun(run_dir=run, config=config, checkpoint=checkpoint, task=built, net=net.eval())


def _contact_model_net(run: Path, config: dict, checkpoint: Path, task: Task) -> nn.Module:
    """A model trained by ``diffcontact train`` (``diffcontact.models.MODEL_NAMES``) from its Lightning checkpoint;
    the contact models with the default contact solver, raising on failure (training counted failures and
    continued; evaluation must not)."""
    from diffcontact.models import ContactModelNet
    from diffcontact.solver import ContactSolver
    from diffcontact.train.module import ContactLightningModule

    try:
        module = ContactLightningModule.load_from_checkpoint(checkpoint, map_location="cpu")
    except Exception as err:  # (torch.load and Lightning raise many types for a damaged file)
        raise ConfigError(f"{checkpoint}: not a loadable checkpoint ({type(err).__name__}: {err})") from err
    trained_on = module.hparams.get("task")
    if trained_on != config["args"]["task"] or module.hparams.get("model") != config["args"]["model"]:
        raise ConfigError(
            f"{checkpoint} holds {module.hparams.get('model')} trained on task {trained_on!r}, but {run}/config.json "
            f"records {config['args']['model']} on {config['args']['task']!r}"
        )
    net = module.net
    if isinstance(net, ContactModelNet):  # (a model of the module without the contact solver keeps its own step)
        sim = net.simulator
        sim.contact_model = dataclasses.replace(sim.contact_model, solver=ContactSolver())
    return net


def _register_builtin_models() -> None:
    """The models of the package (every process that evaluates sees them; a new model family adds its line here)."""
    from diffcontact.models import BASELINE_NAMES, MODEL_NAMES

    register_model((*MODEL_NAMES, *BASELINE_NAMES), _contact_model_net)


_register_builtin_models()
