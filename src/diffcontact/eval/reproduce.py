"""``diffcontact reproduce``: train (or reuse) and evaluate the matrix of tasks x models x seeds, then write the report.

Layout of ``OUT/``: ``runs/TASK/MODEL/seedS/`` (a ``diffcontact train`` run directory, with ``eval/`` from
``diffcontact evaluate``, ``reproduce.log`` and ``reproduce.json``), ``figures/``, ``report.md`` and
``reproduce.json`` (the settings and the wall time of each session).  Every run is one subprocess with one thread
(``diffcontact.eval.worker``: ``train_run`` with the default preset, then ``evaluate_run``), ``jobs`` at a time.
It is resumable: an evaluated run is skipped, a trained one only evaluated, an interrupted training continues from
its last checkpoint.  A model without a training entry point (the baselines until they land) and without a run is
a row marked missing.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from diffcontact.config import available_tasks
from diffcontact.data.noise import check_noise
from diffcontact.errors import ConfigError
from diffcontact.eval.backends import Backend, cell_runner
from diffcontact.eval.evaluate import evaluated
from diffcontact.eval.report import write_report
from diffcontact.files import write_json
from diffcontact.models import ALL_MODELS
from diffcontact.run_dir import RunDir
from diffcontact.systems.registry import BENCHMARK_TASKS
from diffcontact.threads import thread_env

# --quick: tiny datasets, one epoch, short rollouts (tests the pipeline, not the method)
QUICK = {"n_train": 16, "n_val": 4, "n_test": 5, "frames": 30, "epochs": 1, "batch_size": 8, "eval_frames": 20}


@dataclass(frozen=True)
class Cell:
    """One (task, model, seed) of the matrix, its run directory and what is left to do: "done", "train" (then
    evaluate) or "evaluate"."""

    task: str
    model: str
    seed: int
    run: Path
    todo: str
    epochs: int | None = None  # (None: the preset's, or one with --quick)
    pictures: bool = True  # (the evaluation's GIF and figures)

    @property
    def label(self) -> str:
        return f"{self.task}/{self.model}/seed{self.seed}"


def plan(out: Path, tasks: list[str], models: list[str], seeds: list[int]) -> list[Cell]:
    """Every cell of the matrix with what is left to do, tasks outermost."""
    cells = []
    for task in tasks:
        for model in models:
            for seed in seeds:
                run = RunDir.of_cell(out, task, model, seed).path
                if evaluated(run, task, model):
                    cells.append(Cell(task, model, seed, run, "done"))
                else:
                    cells.append(Cell(task, model, seed, run, "evaluate" if RunDir(run).learned.is_file() else "train"))
    return cells


def run_cell(cell: Cell, data: Path, quick: bool, threads: int = 1) -> dict:
    """Train (if not trained yet) and evaluate one cell in a subprocess with ``threads`` threads
    (``diffcontact.eval.worker``, output to ``run/reproduce.log``); writes and returns ``run/reproduce.json``
    ({"status": "done" | "failed", "seconds"[, "error"]})."""
    env = dict(thread_env(threads), PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "diffcontact.eval.worker", cell.task, cell.model, str(cell.seed), str(cell.run)]
    cmd += [str(data), *(["--train"] if cell.todo == "train" else [])]
    epochs = cell.epochs or (QUICK["epochs"] if quick else None)
    cmd += ["--epochs", str(epochs)] if epochs else []
    cmd += [] if cell.pictures else ["--no-pictures"]
    if quick:
        cmd += ["--batch-size", str(QUICK["batch_size"]), "--frames", str(QUICK["eval_frames"])]
    cell.run.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    run = RunDir(cell.run)
    with open(run.reproduce_log, "a") as log:
        log.write(f"$ {' '.join(cmd)}\n")
        log.flush()
        code = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    record = {"status": "done" if code == 0 else "failed", "seconds": time.perf_counter() - t0}
    if code:
        record["error"] = f"exited with {code}; see {run.reproduce_log}"
    write_json(run.reproduce_record, record)
    return record


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


class Progress:
    """Which runs are going, how many are done, and the time left.

    ``expected``: the expected seconds of a run by label (:func:`expected_seconds`: earlier runs of the same model
    and task in OUT); a run without one counts as the mean of the runs finished in this session.  ``runs``: the run
    directory of each label; a running run whose epochs have advanced in this session is shown at its epoch, and
    the time its training has left is its pace so far times the epochs it has left."""

    def __init__(
        self,
        total: int,
        done: int,
        jobs: int,
        echo: Callable[[str], None],
        expected: dict[str, float] | None = None,
        pending: list[str] | None = None,
        runs: dict[str, Path] | None = None,
    ):
        self.total, self.done, self.jobs, self.echo = total, done, jobs, echo
        self.expected = dict(expected or {})
        self.waiting = list(pending) if pending is not None else []  # (labels not started yet)
        self.started = time.perf_counter()
        self.running: dict[str, float] = {}
        self.runs = {label: RunDir(path) for label, path in (runs or {}).items()}
        self.first_epoch: dict[str, int] = {}  # (the epoch a running run had begun when it started here)
        self.durations: list[float] = []
        self.lock = threading.Lock()

    def start(self, label: str) -> None:
        epochs = self._epochs(label)
        with self.lock:
            self.running[label] = time.perf_counter()
            self.first_epoch[label] = epochs[0] if epochs else 0
            if label in self.waiting:
                self.waiting.remove(label)
        self.show()

    def finish(self, label: str, status: str) -> None:
        with self.lock:
            self.durations.append(time.perf_counter() - self.running.pop(label))
            self.done += 1
        self.echo(f"{label}: {status} in {_duration(self.durations[-1])}")
        self.show()

    def left(self) -> float | None:
        """Estimated seconds left, spread over the jobs: each run's expected time (else the mean run time of this
        session), less what a running one has had; None while a run has no estimate."""
        mean = sum(self.durations) / len(self.durations) if self.durations else None
        now = time.perf_counter()
        unnamed = self.total - self.done - len(self.running) - len(self.waiting)  # (counted, not named)
        guesses = [self.expected.get(k, mean) for k in self.waiting] + [mean] * unnamed
        running = [self._running_left(k, now - t, mean) for k, t in self.running.items()]
        known = [g for g in guesses if g is not None]
        if len(known) < len(guesses) or any(r is None for r in running):
            return None
        return (sum(known) + sum(r for r in running if r is not None)) / self.jobs

    def _epochs(self, label: str) -> tuple[int, int] | None:
        """(epochs begun, planned) of a labelled run (``RunDir.epochs``), None where unknown."""
        return self.runs[label].epochs() if label in self.runs else None

    def _running_left(self, label: str, spent: float, mean: float | None) -> float | None:
        """Seconds a running run has left: from its epochs' pace where they advanced here, else its expected
        time less what it has had."""
        epochs = self._epochs(label)
        if epochs is not None and epochs[0] > self.first_epoch.get(label, 0):
            pace = spent / (epochs[0] - self.first_epoch.get(label, 0))
            return pace * max(epochs[1] - epochs[0], 0)
        guess = self.expected.get(label, mean)
        return None if guess is None else max(guess - spent, 0.0)

    def _running(self, label: str, spent: float) -> str:
        epochs = self._epochs(label)
        at = f"epoch {epochs[0]}/{epochs[1]}, " if epochs is not None else ""
        return f"{label} ({at}{_duration(spent)})"

    def show(self) -> None:
        with self.lock:
            now = time.perf_counter()
            going = ", ".join(self._running(k, now - t) for k, t in self.running.items()) or "none"
            left = self.left()
        eta = "unknown until a run finishes" if left is None else f"about {_duration(left)}"
        self.echo(
            f"[{self.done}/{self.total} done] running: {going}; elapsed {_duration(now - self.started)}; left: {eta}"
        )


def expected_seconds(out: Path, cells: list[Cell]) -> dict[str, float]:
    """The expected seconds of each cell to do, from the finished runs in OUT/runs: a training, the mean training
    time (learned.json, all sessions) of the same model's runs scaled by the task's (the mean over its finished
    runs relative to all runs' mean), plus an evaluation's mean time (eval/metrics.json); an evaluation alone, the
    latter.  Cells with nothing to go by are left out."""
    trained, evaluations = [], []
    for learned in out.glob("runs/*/*/seed*/learned.json"):
        train, evaluation = RunDir(learned.parent).times()
        if train is None:
            continue
        trained.append((learned.parts[-4], learned.parts[-3], train))
        if evaluation is not None:
            evaluations.append(evaluation)
    evaluation = sum(evaluations) / len(evaluations) if evaluations else None
    if not trained:
        return {}
    overall = sum(t for *_, t in trained) / len(trained)

    def mean(items: list[float]) -> float | None:
        return sum(items) / len(items) if items else None

    expected = {}
    for c in cells:
        if c.todo == "evaluate" and evaluation is not None:
            expected[c.label] = evaluation
        elif c.todo == "train":
            model = mean([t for _, m, t in trained if m == c.model])
            task = mean([t for k, _, t in trained if k == c.task])
            if model is not None:
                expected[c.label] = model * (task / overall if task else 1.0) + (evaluation or 0.0)
    return expected


def _settings_file(out: Path, quick: bool, noise: float, n_train: int | None = None) -> dict:
    """OUT/reproduce.json, checked to be of the same mode (quick or full), noise and number of training trajectories
    (None: the default sizes): their runs must not mix."""
    path = out / "reproduce.json"
    if path.is_file():
        saved = json.loads(path.read_text())
        if saved.get("n_train") != n_train:
            raise ConfigError(
                f"{out} holds a reproduction with {saved.get('n_train') or 'the default number of'} training "
                f"trajectories: give another --out for {n_train or 'the default number'}"
            )
        if saved.get("quick") != quick:
            mode = "quick" if saved.get("quick") else "full"
            raise ConfigError(
                f"{out} holds a {mode} reproduction: give another --out for a {'quick' if quick else 'full'} one"
            )
        if saved.get("noise", 0.0) != noise:
            raise ConfigError(
                f"{out} holds a reproduction on data with noise {saved.get('noise', 0.0):g}: give another --out for "
                f"noise {noise:g}"
            )
        return saved
    return {"quick": quick, "noise": noise, "n_train": n_train, "sessions": []}


def reproduce(
    tasks: list[str] | None = None,
    models: list[str] | None = None,
    seeds: list[int] | None = None,
    out: str | Path = "reproduction",
    *,
    quick: bool = False,
    jobs: int = 1,
    threads: int = 1,
    data: str | Path | None = None,
    noise: float = 0.0,
    n_train: int | None = None,
    backend: Backend | None = None,
    epochs: int | Mapping[str, int | None] | None = None,
    progress_every: float = 60.0,
    echo: Callable[[str], None] = print,
    command: str = "",
) -> Path:
    """Generate the datasets where missing, train and evaluate every cell not done yet (``jobs`` at a time), then
    write OUT/report.md (:func:`diffcontact.eval.report.write_report`).  Returns the report's path.

    ``threads``: threads of each run's process.  ``data``: dataset root (default ``data``, or OUT/data with
    ``quick``, ``noise`` or ``n_train``).  ``noise``: the standard deviation of the observation noise on the training
    and validation chunks (:mod:`diffcontact.data.noise`; the test trajectories stay clean).  ``n_train``: training
    trajectories of every dataset (default: the generator's, or the quick mode's).  ``backend``: where the
    cells run (:mod:`diffcontact.eval.backends`; default this machine), ``jobs`` of them at a time.  ``epochs``: of
    every run trained, or of each model's runs ({model: epochs}; a model not in it takes its default) (default: each
    task's preset, or one with ``quick``).  ``progress_every``:
    seconds between progress lines while runs are going (one is also printed whenever a run starts or ends).
    """
    from diffcontact.data.generate import generate_dataset

    tasks, models, seeds = list(tasks or BENCHMARK_TASKS), list(models or ALL_MODELS), list(seeds or [0])
    for task in tasks:
        if task not in available_tasks():
            raise ConfigError(f"task {task!r} is not one of {available_tasks()}")
    for model in models:
        if model not in ALL_MODELS:
            raise ConfigError(f"model {model!r} is not one of {list(ALL_MODELS)}")
    if jobs < 1:
        raise ConfigError(f"jobs = {jobs} is not >= 1")
    if threads < 1:
        raise ConfigError(f"threads = {threads} is not >= 1")
    by_model = dict(epochs) if isinstance(epochs, Mapping) else {model: epochs for model in models}
    for value in by_model.values():
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ConfigError(f"epochs = {value!r} is not a whole number >= 1")
    noise = check_noise(noise)
    if n_train is not None and (isinstance(n_train, bool) or not isinstance(n_train, int) or n_train < 1):
        raise ConfigError(f"n_train = {n_train!r} is not a whole number >= 1")
    backend = backend or Backend()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings = _settings_file(out, quick, noise, n_train)
    data = Path(data) if data else (out / "data" if quick or noise or n_train else Path("data"))
    started, began = time.perf_counter(), time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    sizes: dict[str, Any] = {k: QUICK[k] for k in ("n_train", "n_val", "n_test", "frames")} if quick else {}
    if n_train is not None:
        sizes["n_train"] = n_train
    for task in tasks:
        generate_dataset(task, data, noise=noise, progress=False, echo=echo, **sizes)
    cells = [replace(c, epochs=by_model.get(c.model)) for c in plan(out, tasks, models, seeds)]
    todo = [c for c in cells if c.todo in ("train", "evaluate")]
    done = sum(c.todo == "done" for c in cells)
    jobs = min(jobs, max(len(todo), 1))  # (a cluster backend may have every cell in flight)
    progress = Progress(
        len(todo) + done, done, jobs, echo, expected_seconds(out, todo), pending=[c.label for c in todo],
        runs={c.label: c.run for c in todo},
    )  # fmt: skip

    runner = cell_runner(backend, out, threads)

    def job(cell: Cell) -> dict:
        progress.start(cell.label)
        try:
            record = runner(cell, data, quick)
        except Exception as err:  # (an OS error starting a subprocess, a cluster's job lost: the other runs go on)
            record = {"status": "failed", "error": f"{type(err).__name__}: {err}"}
        progress.finish(cell.label, record["status"] + (f" ({record['error']})" if "error" in record else ""))
        return record

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        pending = {pool.submit(job, c) for c in todo}
        while pending:
            finished, pending = wait(pending, timeout=progress_every, return_when=FIRST_COMPLETED)
            if pending and not finished:  # (a start or an end shows the progress itself)
                progress.show()
    settings["sessions"].append(
        {
            "started": began,
            "seconds": time.perf_counter() - started,
            "runs": len(todo),
            "command": command,
            "backend": backend.name,
        }
    )
    settings["data"] = str(data)
    write_json(out / "reproduce.json", settings)
    report = write_report(out, tasks, models, seeds, settings)
    echo(f"report: {report}")
    return report
