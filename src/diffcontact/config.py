"""Task configs: find, load and validate task files (the packaged ones in ``diffcontact/tasks/*.toml``, or any
file given by its path).

A task file has a ``[task]`` table (name, system builder, dt, frames, dtype, deviations) and one table per
part of the system (``bodies``, ``contact``, ``potential``, ``walls``, ``init`` and system-specific ones).
Every value is checked at this boundary; an invalid one raises :class:`ConfigError` naming the field, e.g.
``ConfigError: contact.cor = 1.3 is not in [0, 1]``; so does a table or key the task's system does not read
(:func:`check_keys`: a typo never silently means a default).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomllib

from diffcontact.errors import ConfigError

_ENV_DIR = "DIFFCONTACT_TASKS"
MAX_FRAMES = 1_000_000  # frames of one trajectory (task.frames): 10^4 s at dt = 0.01
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")

# Tables every task file may hold, with their keys (None: the keys are checked by their reader, here
# ``diffcontact train`` against its presets, train/config.py: task_training).  A system adds its own tables
# (systems/registry.py: register_system).
COMMON_TABLES: dict[str, tuple[str, ...] | None] = {
    "task": ("name", "system", "dt", "frames", "dtype", "deviations", "substeps"),
    "contact": ("mu", "cor", "compensation", "compensation_lift", "time_of_impact"),
    "training": None,
}


def tasks_dir() -> Path:
    """Directory of the packaged task files: ``$DIFFCONTACT_TASKS`` or the package's ``tasks/`` folder."""
    env = os.environ.get(_ENV_DIR)
    if env:
        return Path(env)
    return Path(__file__).resolve().parent / "tasks"


def available_tasks() -> list[str]:
    """Names of the tasks found in :func:`tasks_dir` (file stems), sorted."""
    folder = tasks_dir()
    return sorted(p.stem for p in folder.glob("*.toml")) if folder.is_dir() else []


@dataclass(frozen=True)
class TaskConfig:
    """A validated task: ``raw`` is the parsed TOML (kept verbatim so outputs can record it)."""

    name: str
    system: str
    dt: float
    frames: int
    dtype: str
    raw: dict[str, Any] = field(repr=False)
    source: str = ""
    ref: str = ""  # how to find the task again: a packaged task's name or a task file's absolute path

    def section(self, key: str) -> Section:
        """The table ``key`` (an empty one if absent) wrapped for validated access."""
        value = self.raw.get(key, {})
        if not isinstance(value, dict):
            raise ConfigError(f"{key} must be a table, got {value!r}")
        return Section(key, value)

    @property
    def toml_text(self) -> str:
        """The task file's text (for recording alongside outputs)."""
        return self.source


class Section:
    """Validated getters for one config table; errors name the dotted field."""

    def __init__(self, prefix: str, data: dict[str, Any]):
        self.prefix = prefix
        self.data = data

    def _name(self, key: str) -> str:
        return f"{self.prefix}.{key}"

    def has(self, key: str) -> bool:
        return key in self.data

    def get(self, key: str, default: Any = None) -> Any:
        return self.data.get(key, default)

    def number(
        self,
        key: str,
        default: float | None = None,
        *,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
    ) -> float:
        """A finite real in [lo, hi] (or (lo, hi] with ``lo_open``)."""
        if key not in self.data:
            if default is None:
                raise ConfigError(f"{self._name(key)} is missing")
            return float(default)
        return _check_real(self._name(key), self.data[key], lo, hi, lo_open)

    def integer(self, key: str, default: int | None = None, *, lo: int | None = None) -> int:
        if key not in self.data:
            if default is None:
                raise ConfigError(f"{self._name(key)} is missing")
            return int(default)
        value = self.data[key]
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{self._name(key)} = {value!r} is not an integer")
        if lo is not None and value < lo:
            raise ConfigError(f"{self._name(key)} = {value} is smaller than {lo}")
        return value

    def numbers(
        self,
        key: str,
        *,
        length: int | tuple[int, ...] | None = None,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
        default: list[float] | None = None,
        nonempty: bool = False,
    ) -> list[float]:
        """A list of finite reals, each in range, of an allowed length (an int or a tuple of ints), with at least
        one value if ``nonempty``."""
        if key not in self.data:
            if default is None:
                raise ConfigError(f"{self._name(key)} is missing")
            values = list(default)
        else:
            values = self.data[key]
        name = self._name(key)
        if isinstance(values, (int, float)) and not isinstance(values, bool):
            values = [values]
        if not isinstance(values, list):
            raise ConfigError(f"{name} = {values!r} is not a list of numbers")
        if nonempty and not values:
            raise ConfigError(f"{name} is empty: at least one value is needed")
        allowed = (length,) if isinstance(length, int) else length
        if allowed is not None and len(values) not in allowed:
            want = " or ".join(str(n) for n in allowed)
            raise ConfigError(f"{name} has {len(values)} values, expected {want}")
        return [_check_real(f"{name}[{i}]", v, lo, hi, lo_open) for i, v in enumerate(values)]

    def matrix(self, key: str, *, cols: int, default: list[list[float]] | None = None) -> list[list[float]]:
        """A list of rows of ``cols`` finite reals."""
        rows = self.data.get(key, default)
        name = self._name(key)
        if rows is None:
            raise ConfigError(f"{name} is missing")
        if not isinstance(rows, list):
            raise ConfigError(f"{name} = {rows!r} is not a list of rows")
        out = []
        for i, row in enumerate(rows):
            if not isinstance(row, list) or len(row) != cols:
                raise ConfigError(f"{name}[{i}] = {row!r} is not a row of {cols} numbers")
            out.append([_check_real(f"{name}[{i}][{j}]", v, None, None, False) for j, v in enumerate(row)])
        return out

    def flag(self, key: str, default: bool) -> bool:
        """A boolean (TOML true/false)."""
        value = self.data.get(key, default)
        if not isinstance(value, bool):
            raise ConfigError(f"{self._name(key)} = {value!r} is not true or false")
        return value

    def choice(self, key: str, options: tuple[str, ...], default: str | None = None) -> str:
        value = self.data.get(key, default)
        if value not in options:
            raise ConfigError(f"{self._name(key)} = {value!r} is not one of {list(options)}")
        return value


def _check_real(name: str, value: Any, lo: float | None, hi: float | None, lo_open: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{name} = {value!r} is not a number")
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(f"{name} = {value} is not finite")
    if lo is not None and hi is not None and (value < lo or value > hi or (lo_open and value == lo)):
        left = "(" if lo_open else "["
        raise ConfigError(f"{name} = {value:g} is not in {left}{lo:g}, {hi:g}]")
    if lo is not None and (value < lo or (lo_open and value == lo)):
        word = "positive" if lo == 0 and lo_open else f">= {lo:g}"
        raise ConfigError(f"{name} = {value:g} is not {word}")
    if hi is not None and value > hi:
        raise ConfigError(f"{name} = {value:g} is not <= {hi:g}")
    return value


def load_task(task: str | Path, overrides: dict[str, dict[str, Any]] | None = None) -> TaskConfig:
    """The one way from a command's task argument to a validated config: a packaged task's name (``BP5-e``) or
    the path of a task file (``./my_task.toml``: anything ending in ``.toml`` or holding a path separator).

    ``overrides`` maps table -> {key: value} and is applied before validation (used by tests and sweeps).
    The config's ``ref`` is the name or the file's absolute path, so that the task is found again from any
    directory.  System-specific tables are validated when the System is built (:func:`diffcontact.build_task`).
    """
    text_arg = str(task)
    is_file = isinstance(task, Path) or text_arg.endswith(".toml") or any(s in text_arg for s in ("/", os.sep))
    if is_file:
        path = Path(task).expanduser()
        if not path.is_file():
            raise ConfigError(f"task file {text_arg!r} does not exist (or is not a file)")
        ref = str(path.resolve())
    else:
        path, ref = tasks_dir() / f"{text_arg}.toml", text_arg
        if not path.is_file():
            raise ConfigError(
                f"unknown task {text_arg!r}; available tasks: {', '.join(available_tasks())} (or give the path of a "
                "task file, e.g. ./my_task.toml)"
            )
    try:
        text = path.read_text()
        raw = tomllib.loads(text)
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read the task file: {err}") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: invalid TOML: {err}") from err
    for table, values in (overrides or {}).items():
        raw.setdefault(table, {}).update(values)
    return task_from_dict(raw, source=text, ref=ref)


def task_from_dict(raw: dict[str, Any], source: str = "", ref: str = "") -> TaskConfig:
    """Validate the ``[task]`` table of an already parsed config (``ref``: default the task's name)."""
    task = Section("task", raw.get("task", {}))
    check_keys({"task": task.data}, COMMON_TABLES)
    name = task.get("name")
    if not isinstance(name, str) or not name:
        raise ConfigError("task.name is missing")
    if not _SAFE_NAME.fullmatch(name) or name in (".", ".."):
        raise ConfigError(
            f"task.name = {name!r} is not a safe folder name (outputs go to OUT/NAME/): use 1 to 100 letters, "
            "digits, '.', '_' or '-', starting with a letter or digit"
        )
    system = task.get("system")
    if not isinstance(system, str):
        raise ConfigError("task.system is missing")
    dt = task.number("dt", lo=0.0, lo_open=True)
    frames = task.integer("frames", lo=2)
    if frames > MAX_FRAMES:
        raise ConfigError(
            f"task.frames = {frames} is more than {MAX_FRAMES} (a trajectory of {frames * dt:g} s); simulate long "
            "motions as several shorter trajectories"
        )
    dtype = task.choice("dtype", ("float64", "float32"), default="float64")
    return TaskConfig(
        name=name, system=system, dt=dt, frames=frames, dtype=dtype, raw=raw, source=source, ref=ref or name
    )


def check_keys(raw: dict[str, Any], tables: dict[str, tuple[str, ...] | None], system: str = "") -> None:
    """ConfigError naming the first table of ``raw`` not in ``tables``, or key not among its table's allowed keys
    (``tables``: table -> allowed keys, None for a table whose keys its reader checks)."""
    for table, value in raw.items():
        if table not in tables:
            of = f" of a {system!r} task" if system else ""
            raise ConfigError(f"[{table}] is not a table{of}; allowed tables: {', '.join(tables)}")
        if not isinstance(value, dict):
            raise ConfigError(f"{table} must be a table, got {value!r}")
        allowed = tables[table]
        if allowed is None:
            continue
        for key in value:
            if key not in allowed:
                raise ConfigError(f"{table}.{key} is not a key of [{table}]; allowed keys: {', '.join(allowed)}")


def check_array_size(what: str, values: int, limit: int | None = None) -> None:
    """ConfigError if ``values`` float64 numbers (e.g. N trajectories x T frames x D coordinates, for x and v)
    would take more than ``limit`` bytes (default: half the machine's memory); the message gives the estimate."""
    size = 8 * values
    if limit is None:
        try:
            limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
        except (ValueError, OSError, AttributeError):  # (not on this platform: no bound)
            return
    if size > limit:
        raise ConfigError(
            f"{what} would hold {size / 2**30:.3g} GiB of float64 arrays, more than the {limit / 2**30:.3g} GiB "
            "allowed (half of this machine's memory): use fewer trajectories or frames"
        )
