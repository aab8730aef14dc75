"""A training run's folder, and the one place that names its files.

Layout of a run (``diffcontact train --out RUN``):
- ``config.json``: ``{"args": {"task", "model", ... every setting}, "versions", "parallel"}``, written first;
- ``checkpoints/``: ``last.ckpt`` (resume) and ``best-epoch=E.ckpt`` (chosen on the validation split);
- ``coef_start.json``: the scan of μ and e's start, where the run used one;
- ``learned.json``: what the run learned, its counters and wall time, written last (a finished training);
- ``logs/`` (CSV, TensorBoard) and ``loss.png``;
- ``eval/``: ``metrics.json`` (written last: a finished evaluation), the rollouts and figures.

``diffcontact reproduce`` keeps the run of (task, model, seed) in ``OUT/runs/TASK/MODEL/seedS``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from diffcontact.errors import ConfigError

CONFIG = "config.json"
LEARNED = "learned.json"
COEF_START = "coef_start.json"
CHECKPOINTS = "checkpoints"
LAST_CHECKPOINT = "last.ckpt"
METRICS = "metrics.json"
EVAL = "eval"
SOLVER_FAILURES = "solver_failures.npz"


@dataclass(frozen=True)
class RunDir:
    """The folder ``path`` of one training run (it need not exist yet)."""

    path: Path

    def __init__(self, path: str | Path) -> None:
        object.__setattr__(self, "path", Path(path))

    @classmethod
    def of_cell(cls, out: str | Path, task: str, model: str, seed: int) -> RunDir:
        """The run of (task, model, seed) under a ``diffcontact reproduce`` folder ``out``."""
        return cls(Path(out) / "runs" / task / model / f"seed{seed}")

    @property
    def config(self) -> Path:
        return self.path / CONFIG

    @property
    def learned(self) -> Path:
        return self.path / LEARNED

    @property
    def coef_start(self) -> Path:
        return self.path / COEF_START

    @property
    def solver_failures(self) -> Path:
        """The contact problems the solver failed on in training (``contact_solver.save_failed``), if any."""
        return self.path / SOLVER_FAILURES

    @property
    def checkpoints(self) -> Path:
        return self.path / CHECKPOINTS

    @property
    def last_checkpoint(self) -> Path:
        return self.checkpoints / LAST_CHECKPOINT

    def eval_dir(self, name: str = EVAL) -> Path:
        """The folder of an evaluation of the run (``eval``: the test split's, the default)."""
        return self.path / name

    def read_config(self) -> dict:
        """``config.json``, checked to name a task and a model (ConfigError otherwise)."""
        if not self.config.is_file():
            raise ConfigError(f"{self.path} is not a run directory: {CONFIG} is missing")
        try:
            config = json.loads(self.config.read_text())
            task, model = config["args"]["task"], config["args"]["model"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ConfigError(f"{self.config} is unreadable or lacks args.task / args.model: {err!r}") from err
        if not isinstance(task, str) or not isinstance(model, str):
            raise ConfigError(f"{self.config}: args.task = {task!r} and args.model = {model!r} must be names")
        return config

    def read_learned(self) -> dict:
        """``learned.json`` of a finished training (ConfigError if it is missing or not a JSON object)."""
        try:
            learned = json.loads(self.learned.read_text())
        except (OSError, ValueError) as err:
            raise ConfigError(f"{self.path} is not a finished training run ({LEARNED}): {err}") from err
        if not isinstance(learned, dict):
            raise ConfigError(f"{self.learned} is not a JSON object")
        return learned

    def best_checkpoint(self) -> Path:
        """The checkpoint chosen on the validation split: the one ``learned.json`` names (looked up in the run's
        own checkpoints/ folder if the run was moved), else the only ``checkpoints/best-*.ckpt``."""
        if self.learned.is_file():
            named = self.read_learned().get("best_checkpoint") or ""
            for path in (Path(named), self.checkpoints / Path(named).name):
                if named and path.is_file():
                    return path
            raise ConfigError(f"{self.path}: the best checkpoint {named!r} named in {LEARNED} is missing")
        found = sorted(self.checkpoints.glob("best-*.ckpt"))
        if len(found) != 1:
            raise ConfigError(
                f"{self.path}: expected one {CHECKPOINTS}/best-*.ckpt of a trained run, found {len(found)}"
            )
        return found[0]

    def metrics(self, name: str = EVAL) -> dict | None:
        """The metrics of a finished evaluation (``name``/metrics.json), or None if there is none readable."""
        try:
            metrics = json.loads((self.eval_dir(name) / METRICS).read_text())
        except (OSError, ValueError):
            return None
        return metrics if isinstance(metrics, dict) else None

    def times(self) -> tuple[float | None, float | None]:
        """Training wall time (learned.json, over all the sessions of a resumed run) and the evaluation's
        (eval/metrics.json), in s (None: unknown)."""
        times: list[float | None] = []
        for path, key in ((self.learned, "wall_time_s"), (self.eval_dir() / METRICS, "seconds")):
            try:
                times.append(float(json.loads(path.read_text())[key]))
            except (OSError, ValueError, KeyError, TypeError):
                times.append(None)
        return times[0], times[1]
