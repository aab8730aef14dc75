"""A training run's folder, and the one place that names its files.

Layout of a run (``diffcontact train --out RUN``; ``train.run.train_run`` writes it, only its first process in a DDP
run, which holds the folder's lock, ``lock.output_lock``, while it writes):
- ``config.json``: ``{"args": {"task", "model", ... every setting}, "versions", "parallel"}`` (the settings,
  the versions and how the processes share the work), written first;
- ``checkpoints/``: ``last.ckpt`` (resume; written atomically at the end of every epoch) and ``best-epoch=E.ckpt``
  (chosen on the validation loss; the last epoch's where a run learns its first states in noise coordinates),
  ``refined-best-epoch=E.ckpt`` where refining μ and e kept a change;
- ``coef_start.json``: the scan of μ and e's start, where the run used one;
- ``solver_failures.npz``: the first contact problems the solver failed on, if any;
- ``learned.json``: what the run learned, its counters and wall time, written last (a finished training);
- ``logs/``: ``csv/`` (CSV, every session of a resumed run) and ``tb/`` (TensorBoard); ``loss.png``, the loss
  curves of the CSV logs;
- ``eval/``: ``metrics.json`` (written last: a finished evaluation), the rollouts (``rollout.npz``,
  ``rollout.gif``; measured tosses: ``predictions.npz``) and figures.

``diffcontact reproduce`` keeps the run of (task, model, seed) in ``OUT/runs/TASK/MODEL/seedS``, with its cell's
``reproduce.json`` (status) and ``reproduce.log`` (the worker's output); ``diffcontact train`` without ``--out``
trains into ``runs/TASK/MODEL/seedS`` (:meth:`RunDir.default`).
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
BEST_PREFIX = "best-"
BEST_CHECKPOINT = BEST_PREFIX + "{epoch}"  # (Lightning's file name template: best-epoch=E.ckpt)
REFINED_PREFIX = "refined-"  # (the best checkpoint with μ and e refined: refined-best-epoch=E.ckpt)
CALIBRATED_PREFIX = "calibrated-"  # (... and μ calibrated on whole measured tosses: calibrated-[refined-]best-…)
SOLVER_FAILURES = "solver_failures.npz"
LOGS = "logs"
CSV_LOGS = "csv"
TB_LOGS = "tb"
LOSS_FIGURE = "loss.png"
REPRODUCE_RECORD = "reproduce.json"
REPRODUCE_LOG = "reproduce.log"
RUNS = "runs"
EVAL = "eval"
# The files of an evaluation's folder (a run's ``eval/``, or any folder an evaluation is written to).
METRICS = "metrics.json"
PREDICTIONS = "predictions.npz"
ROLLOUT = "rollout.npz"
ROLLOUT_GIF = "rollout.gif"


@dataclass(frozen=True)
class RunDir:
    """The folder ``path`` of one training run (it need not exist yet)."""

    path: Path

    def __init__(self, path: str | Path) -> None:
        object.__setattr__(self, "path", Path(path))

    @classmethod
    def of_cell(cls, out: str | Path, task: str, model: str, seed: int) -> RunDir:
        """The run of (task, model, seed) under a ``diffcontact reproduce`` folder ``out``."""
        return cls(Path(out) / RUNS / task / model / f"seed{seed}")

    @classmethod
    def default(cls, task: str, model: str, seed: int) -> RunDir:
        """Where ``diffcontact train`` trains without ``--out``: ``runs/TASK/MODEL/seedS`` in the current folder."""
        return cls(Path(RUNS) / task / model / f"seed{seed}")

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

    @property
    def logs(self) -> Path:
        return self.path / LOGS

    @property
    def csv_logs(self) -> Path:
        """The CSV logs (Lightning's ``CSVLogger``: a ``version_N/metrics.csv`` a session)."""
        return self.logs / CSV_LOGS

    @property
    def tb_logs(self) -> Path:
        """The TensorBoard logs (Lightning's ``TensorBoardLogger``)."""
        return self.logs / TB_LOGS

    @property
    def loss_figure(self) -> Path:
        """The loss curves of the CSV logs (``train.run.plot_losses``)."""
        return self.path / LOSS_FIGURE

    @property
    def reproduce_record(self) -> Path:
        """A ``diffcontact reproduce`` cell's status (``eval.reproduce.run_cell``)."""
        return self.path / REPRODUCE_RECORD

    @property
    def reproduce_log(self) -> Path:
        """A ``diffcontact reproduce`` cell's output (its worker's, appended at every attempt)."""
        return self.path / REPRODUCE_LOG

    def eval_dir(self, name: str = EVAL) -> Path:
        """The folder of an evaluation of the run (``eval``: the test split's, the default)."""
        return self.path / name

    def metrics_file(self, name: str = EVAL) -> Path:
        """The metrics of the evaluation ``name`` (written last: its presence marks a finished evaluation)."""
        return self.eval_dir(name) / METRICS

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
        found = sorted(self.checkpoints.glob(f"{BEST_PREFIX}*.ckpt"))
        if len(found) != 1:
            raise ConfigError(
                f"{self.path}: expected one {CHECKPOINTS}/best-*.ckpt of a trained run, found {len(found)}"
            )
        return found[0]

    def metrics(self, name: str = EVAL) -> dict | None:
        """The metrics of a finished evaluation (``name``/metrics.json), or None if there is none readable."""
        try:
            metrics = json.loads(self.metrics_file(name).read_text())
        except (OSError, ValueError):
            return None
        return metrics if isinstance(metrics, dict) else None

    def epochs(self) -> tuple[int, int] | None:
        """(epochs begun, epochs planned) of a run in training: the epoch of the last row of its newest CSV log (the
        rows of epoch E, counted from 0, begin once E epochs are done) and config.json's ``epochs``; None before
        both are written.  Reads only the log's first and last lines (a long run's log grows to megabytes)."""
        logs = sorted(self.csv_logs.glob("version_*/metrics.csv"), key=lambda p: p.stat().st_mtime)
        try:
            planned = int(json.loads(self.config.read_text())["args"]["epochs"])
            with logs[-1].open("rb") as fh:
                column = fh.readline().decode().strip().split(",").index("epoch")
                fh.seek(max(fh.seek(0, 2) - 65536, 0))
                last = fh.read().decode(errors="replace").strip().splitlines()[-1]
            return int(last.split(",")[column]), planned
        except (OSError, ValueError, KeyError, TypeError, IndexError):
            return None

    def times(self) -> tuple[float | None, float | None]:
        """Training wall time (learned.json, over all the sessions of a resumed run) and the evaluation's
        (eval/metrics.json), in s (None: unknown)."""
        times: list[float | None] = []
        for path, key in ((self.learned, "wall_time_s"), (self.metrics_file(), "seconds")):
            try:
                times.append(float(json.loads(path.read_text())[key]))
            except (OSError, ValueError, KeyError, TypeError):
                times.append(None)
        return times[0], times[1]
