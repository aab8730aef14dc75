"""Task registry: a task file's ``task.system`` names the builder; systems are declared, not special-cased.

A system of your own (docs/custom_systems.md) is a builder ``TaskConfig -> Task`` registered with the tables and
keys its task files may hold: :func:`register_system`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from diffcontact.config import COMMON_TABLES, TaskConfig, check_keys, load_task
from diffcontact.errors import ConfigError
from diffcontact.systems import bouncing, box, gyroscope, pendulum, rope
from diffcontact.systems.base import Stepping, Task


@dataclass(frozen=True)
class SystemKind:
    """A registered builder and the tables (table -> allowed keys) its task files may hold besides
    :data:`diffcontact.config.COMMON_TABLES`."""

    build: Callable[[TaskConfig], Task]
    tables: dict[str, tuple[str, ...]]


SYSTEMS: dict[str, SystemKind] = {}


def register_system(name: str, build: Callable[[TaskConfig], Task], tables: dict[str, tuple[str, ...]]) -> None:
    """Make ``task.system = name`` build with ``build``; a task file of it may hold :data:`COMMON_TABLES` and
    ``tables`` (table -> allowed keys), anything else is a ConfigError.  Registering a name again replaces it."""
    if not isinstance(name, str) or not name:
        raise ConfigError(f"system name {name!r} is not a non-empty string")
    clash = set(tables) & {t for t, keys in COMMON_TABLES.items() if keys is not None}
    if clash:
        raise ConfigError(f"system {name!r}: tables {sorted(clash)} are common to every task and cannot be redefined")
    SYSTEMS[name] = SystemKind(build, {t: tuple(keys) for t, keys in tables.items()})


register_system("bouncing", bouncing.build_bouncing, bouncing.TABLES)
register_system("chain_pendulum", pendulum.build_chain_pendulum, pendulum.TABLES)
register_system("rope", rope.build_rope, rope.TABLES)
register_system("gyroscope", gyroscope.build_gyroscope, gyroscope.TABLES)
register_system("box", box.build_box, box.TABLES)

BENCHMARK_TASKS = ("BP5-e", "BP5", "CP3-e", "CP3", "BD5", "Rope", "Gyro-e", "Gyro")


def build_task(task: str | Path | TaskConfig, overrides: dict[str, dict[str, Any]] | None = None) -> Task:
    """Load (if needed), validate and build a task from a packaged task's name, a task file's path or a config."""
    cfg = task if isinstance(task, TaskConfig) else load_task(task, overrides)
    kind = SYSTEMS.get(cfg.system)
    if kind is None:
        raise ConfigError(f"task.system = {cfg.system!r} is not one of {sorted(SYSTEMS)}")
    check_keys(cfg.raw, {**COMMON_TABLES, **kind.tables}, cfg.system)
    built = kind.build(cfg)
    return replace(built, system=replace(built.system, stepping=stepping(cfg)))


def stepping(cfg: TaskConfig) -> Stepping:
    """The time-stepping scheme of a task file: ``contact.time_of_impact`` (default true: correct gradients through
    impacts; the benchmark task files say false, the published scheme) and ``task.substeps`` (default 1)."""
    toi = cfg.section("contact").flag("time_of_impact", True)
    return Stepping(time_of_impact=toi, substeps=cfg.section("task").integer("substeps", 1, lo=1))
