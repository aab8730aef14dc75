"""Task registry: a task file's ``task.system`` names the builder; systems are declared, not special-cased."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from diffcontact.config import TaskConfig, load_task
from diffcontact.errors import ConfigError
from diffcontact.systems.base import Stepping, Task
from diffcontact.systems.bouncing import build_bouncing
from diffcontact.systems.gyroscope import build_gyroscope
from diffcontact.systems.pendulum import build_chain_pendulum
from diffcontact.systems.rope import build_rope

BUILDERS = {
    "bouncing": build_bouncing,
    "chain_pendulum": build_chain_pendulum,
    "rope": build_rope,
    "gyroscope": build_gyroscope,
}

BENCHMARK_TASKS = ("BP5-e", "BP5", "CP3-e", "CP3", "BD5", "Rope", "Gyro-e", "Gyro")


def build_task(task: str | Path | TaskConfig, overrides: dict[str, dict[str, Any]] | None = None) -> Task:
    """Load (if needed), validate and build a task by name, path or config."""
    cfg = task if isinstance(task, TaskConfig) else load_task(task, overrides)
    builder = BUILDERS.get(cfg.system)
    if builder is None:
        raise ConfigError(f"task.system = {cfg.system!r} is not one of {sorted(BUILDERS)}")
    task = builder(cfg)
    return replace(task, system=replace(task.system, stepping=stepping(cfg)))


def stepping(cfg: TaskConfig) -> Stepping:
    """The time-stepping scheme of a task file: ``contact.time_of_impact`` (default true: correct gradients through
    impacts; the benchmark task files say false, the published scheme) and ``task.substeps`` (default 1)."""
    toi = cfg.section("contact").flag("time_of_impact", True)
    return Stepping(time_of_impact=toi, substeps=cfg.section("task").integer("substeps", 1, lo=1))
