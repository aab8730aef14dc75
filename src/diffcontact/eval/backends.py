"""Where the cells of ``diffcontact reproduce`` run: this machine (``local``, the default: one subprocess per cell,
``jobs`` at a time), a Ray cluster (``ray``), or Slurm through submitit (``slurm``).

Every backend runs the same thing, :func:`diffcontact.eval.reproduce.run_cell`, which starts one worker process
for the cell (``diffcontact.eval.worker``), and the driver writes the same report, whichever backend ran the cells.
A cell is one run directory, locked while it is trained (``diffcontact.lock``), checkpointed every epoch and
resumed from its last checkpoint, and a finished training is never redone (the worker checks for learned.json).
So a cell whose worker dies is simply run again: Ray retries a task whose worker died (``retries`` times), and a
Slurm job that is preempted or runs out of time is requeued by submitit (:class:`CellJob` is checkpointable).  The
worker process dies with the process that started it (``worker.die_with_parent``), so a retry never meets the
previous attempt's trainer still holding the lock.

The cluster backends assume what clusters give: the package installed on every node, and OUT and the dataset root
on a file system every node sees.  Ray and submitit are optional dependencies (``pip install ray submitit``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from diffcontact.errors import ConfigError

BACKENDS = ("local", "ray", "slurm")


@dataclass(frozen=True)
class Backend:
    """Where and how the cells run.

    name: one of ``BACKENDS``.  address: the Ray cluster to join (None: a local Ray cluster is started; "auto":
    the one this node belongs to).  partition, time_min: the Slurm partition and each job's time limit in minutes.
    cluster: submitit's cluster, "slurm" (or "local": the jobs run as local processes, as the tests do).
    retries: how often Ray runs a cell again whose worker died.
    """

    name: str = "local"
    address: str | None = None
    partition: str | None = None
    time_min: int = 240
    cluster: str = "slurm"
    retries: int = 3

    def __post_init__(self) -> None:
        if self.name not in BACKENDS:
            raise ConfigError(f"backend = {self.name!r} is not one of {list(BACKENDS)}")
        if self.address is not None and self.name != "ray":
            raise ConfigError(f"address = {self.address!r} is for --backend ray, not {self.name}")
        if self.partition is not None and self.name != "slurm":
            raise ConfigError(f"partition = {self.partition!r} is for --backend slurm, not {self.name}")
        if isinstance(self.time_min, bool) or not isinstance(self.time_min, int) or self.time_min < 1:
            raise ConfigError(f"time = {self.time_min!r} is not a whole number of minutes >= 1")
        if self.cluster not in ("slurm", "local"):
            raise ConfigError(f"cluster = {self.cluster!r} is not 'slurm' or 'local'")
        if isinstance(self.retries, bool) or not isinstance(self.retries, int) or self.retries < 0:
            raise ConfigError(f"retries = {self.retries!r} is not a whole number >= 0")


def _engine(module: str) -> Any:
    """The optional engine ``module`` (``ray``, ``submitit`` or one of their submodules), imported by name so that the
    package type-checks without it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ConfigError(
            f"--backend {'ray' if module == 'ray' else 'slurm'} needs {module.split('.')[0]}, an optional "
            f"dependency: pip install {module.split('.')[0]}"
        ) from None


class CellJob:
    """One cell as a submitit job: run to the end, or requeued when Slurm preempts it or its time runs out (it
    resumes from the run's last checkpoint)."""

    def __init__(self, cell: Any, data: Path, quick: bool, threads: int):  # (cell: a reproduce.Cell)
        self.cell, self.data, self.quick, self.threads = cell, data, quick, threads

    def __call__(self) -> dict:
        from diffcontact.eval.reproduce import run_cell

        return run_cell(self.cell, self.data, self.quick, self.threads)

    def checkpoint(self) -> Any:  # (submitit's hook on preemption and timeout: the same job again)
        return _engine("submitit.helpers").DelayedSubmission(self)


def cell_runner(backend: Backend, out: Path, threads: int) -> Callable[[Any, Path, bool], dict]:
    """A function that runs one cell (a ``reproduce.Cell``) on ``backend`` to its end and returns its record (as
    ``run_cell``); blocking,
    so the driver's pool of ``jobs`` threads bounds the cells in flight.  ``out``: the sweep's folder (submitit
    writes its job logs under OUT/submitit)."""
    from diffcontact.eval.reproduce import run_cell

    if backend.name == "local":
        return lambda cell, data, quick: run_cell(cell, data, quick, threads)
    if backend.name == "ray":
        ray = _engine("ray")
        if not ray.is_initialized():
            ray.init(address=backend.address, include_dashboard=False, log_to_driver=False, configure_logging=False)
        remote = ray.remote(num_cpus=threads, max_retries=backend.retries)(run_cell)
        return lambda cell, data, quick: ray.get(remote.remote(cell, data, quick, threads))
    executor = _engine("submitit").AutoExecutor(folder=out / "submitit", cluster=backend.cluster)
    settings: dict[str, Any] = {"timeout_min": backend.time_min, "cpus_per_task": threads, "name": "diffcontact"}
    if backend.partition:
        settings["slurm_partition"] = backend.partition
    executor.update_parameters(**settings)
    return lambda cell, data, quick: executor.submit(CellJob(cell, data, quick, threads)).result()
