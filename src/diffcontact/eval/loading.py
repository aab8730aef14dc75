"""Load a trained run for evaluation: its config, best checkpoint and model.

A run directory (:class:`diffcontact.run_dir.RunDir`) records its task and model in ``config.json`` and names its
best checkpoint in ``learned.json``.  Every model ``diffcontact train`` trains (the contact models and the baselines,
``diffcontact.models``) is rebuilt from its Lightning checkpoint, as an ``nn.Module`` with
``forward(x0, v0, frames) -> (xs, vs)``, x0, v0 (B, P, d) and xs, vs (B, frames, P, d) with frame 0 included;
evaluation never branches on the model's name.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from torch import nn

from diffcontact.errors import ConfigError
from diffcontact.run_dir import RunDir
from diffcontact.systems.base import Task


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


def load_run(run: str | Path, task: str | None = None, checkpoint: Path | None = None) -> LoadedRun:
    """Load a run's best model from its checkpoint (``trained_net``), or the model of ``checkpoint`` (another of
    the run's checkpoints, e.g. its last).

    ``task``: the task the caller expects (a packaged task's name or a task file's path, compared by task name); a
    run of another task is a ConfigError, as are a missing config, a model that ``diffcontact train`` does not
    train, and a missing or unreadable checkpoint.
    """
    from diffcontact.config import load_task
    from diffcontact.models import ALL_MODELS
    from diffcontact.systems.registry import build_task

    run = Path(run)
    config = RunDir(run).read_config()
    name, model = config["args"]["task"], config["args"]["model"]
    built = build_task(name)
    if task is not None and built.config.name != load_task(task).name:
        raise ConfigError(f"{run} is a run of task {built.config.name!r}, not {task!r}")
    if model not in ALL_MODELS:
        raise ConfigError(f"{run}: model {model!r} is not one that diffcontact trains: {list(ALL_MODELS)}")
    checkpoint = checkpoint or RunDir(run).best_checkpoint()
    net = trained_net(run, config, checkpoint)
    return LoadedRun(run_dir=run, config=config, checkpoint=checkpoint, task=built, net=net.eval())


def trained_net(run: Path, config: dict, checkpoint: Path) -> nn.Module:
    """The model of the run ``run`` (its config.json ``config``) from its Lightning checkpoint ``checkpoint``; the
    contact models with the default contact solver, raising on failure (training counted failures and continued;
    evaluation must not)."""
    from diffcontact.models import ContactModelNet
    from diffcontact.solver import ContactSolver
    from diffcontact.train.module import ContactLightningModule

    try:
        module = ContactLightningModule.from_checkpoint(checkpoint)
    except Exception as err:  # (torch.load and Lightning raise many types for a damaged file)
        raise ConfigError(f"{checkpoint}: not a loadable checkpoint ({type(err).__name__}: {err})") from err
    trained_on, trained = module.config.task, module.config.model
    if trained_on != config["args"]["task"] or trained != config["args"]["model"]:
        raise ConfigError(
            f"{checkpoint} holds {trained} trained on task {trained_on!r}, but {run}/config.json "
            f"records {config['args']['model']} on {config['args']['task']!r}"
        )
    net = module.net
    if isinstance(net, ContactModelNet):  # (a model of the module without the contact solver keeps its own step)
        sim = net.simulator
        sim.contact_model = dataclasses.replace(sim.contact_model, solver=ContactSolver())
    return net
