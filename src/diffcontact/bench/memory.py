"""Memory benchmark: the resident memory of a task's default training at the end of every epoch.

Each task trains as ``diffcontact train TASK`` does (``train_run``: the default preset and the task's own epochs,
one thread by default) on the dataset ``diffcontact generate TASK`` makes (generated into ``data`` if missing),
in a fresh process of its own (spawned), so that one task's memory does not count in the next one's.  A Lightning
callback reads the process's resident set size (VmRSS of /proc/self/status) at the end of each training epoch.

The first epochs raise the memory anyway (allocator pools, caches); a graph kept alive by a reference cycle raises
it on every epoch after them (the FlatProjection cycle, since fixed, leaked about 24 MB an epoch on Gyro).  So
the growth is measured from epoch ``SETTLE``: the highest RSS of epochs SETTLE..last minus the RSS at epoch SETTLE,
and a task is "flat" if that is at most ``FLAT_MB``.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import TypedDict
from unittest import mock

import lightning
import lightning.pytorch as pl

from diffcontact.config import load_task
from diffcontact.data.generate import generate_dataset, worker_pool
from diffcontact.errors import DiffContactError
from diffcontact.files import versions, write_json, write_text
from diffcontact.systems import BENCHMARK_TASKS

SETTLE = 5  # the epoch from which the memory should stay flat
FLAT_MB = 50.0  # the growth after epoch SETTLE that still counts as flat (MB)


def rss_mb(status: Path = Path("/proc/self/status")) -> float:
    """The resident set size of this process (VmRSS) in MB (10⁶ bytes)."""
    for line in status.read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024 / 1e6  # (the kernel counts kB of 1024 bytes)
    raise DiffContactError(f"{status} has no VmRSS line (not Linux?)")


class EpochMemory(pl.Callback):
    """Appends ``rss_mb()`` to ``rss`` at the end of every training epoch."""

    def __init__(self) -> None:
        self.rss: list[float] = []

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.rss.append(rss_mb())


def _train(task: str, data: str, epochs: int | None, threads: int) -> dict:
    """In a fresh process: ``train_run(task)`` into a temporary folder with an ``EpochMemory`` callback; returns
    the RSS per epoch (MB) and the training's wall time (s)."""
    from diffcontact.threads import set_threads
    from diffcontact.train.module import ContactLightningModule
    from diffcontact.train.run import train_run

    set_threads(threads)
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)
    memory = EpochMemory()
    # (train_run takes no callbacks: the module hands this one to its trainer; this process runs nothing else)
    with (
        mock.patch.object(ContactLightningModule, "configure_callbacks", lambda self: [memory]),
        tempfile.TemporaryDirectory() as tmp,
    ):
        summary = train_run(task, out=Path(tmp) / "run", data_root=data, epochs=epochs, progress=False)
    return {"rss_mb": memory.rss, "wall_time_s": summary["wall_time_s"]}


def summarize(rss: list[float], settle: int = SETTLE, flat_mb: float = FLAT_MB) -> dict:
    """RSS (MB) after epoch 1, epoch ``settle``, the last, the highest, and the growth after epoch ``settle`` with
    its verdict ("flat" or "grows"; None and "too short" for a run of fewer than ``settle`` epochs)."""
    late = rss[settle - 1 :]
    growth = max(late) - late[0] if late else None
    verdict = "too short" if growth is None else "flat" if growth <= flat_mb else "grows"
    return {
        "epochs": len(rss),
        "rss_epoch1_mb": rss[0],
        f"rss_epoch{settle}_mb": late[0] if late else None,
        "rss_last_mb": rss[-1],
        "rss_max_mb": max(rss),
        "growth_mb": growth,
        "verdict": verdict,
    }


COLUMNS = ("rss_epoch1_mb", f"rss_epoch{SETTLE}_mb", "rss_last_mb", "rss_max_mb", "growth_mb")
TABLE = (
    f"| task | epochs | RSS epoch 1 (MB) | epoch {SETTLE} | last | max | growth after epoch {SETTLE} | verdict "
    "| training (s) | load average (start → end) |\n|---|---|---|---|---|---|---|---|---|---|"
)


def _mb(x: float | None) -> str:
    return "–" if x is None else f"{x:.0f}"


def _line(row: dict) -> str:
    """A row of the Markdown table."""
    cells = [row["task"], str(row["epochs"]), *(_mb(row[k]) for k in COLUMNS), row["verdict"]]
    cells += [f"{row['wall_time_s']:.0f}", "{:.2f} → {:.2f}".format(*row["load_average"])]
    return "| " + " | ".join(cells) + " |"


class DatasetSizes(TypedDict, total=False):
    """The sizes of a dataset to generate (keywords of ``generate_dataset``)."""

    n_train: int
    n_val: int
    n_test: int


def run_memory_benchmark(
    tasks: list[str] | None = None,
    epochs: int | None = None,
    data: str = "data",
    out: str | None = None,
    threads: int = 1,
    sizes: DatasetSizes | None = None,
    echo: Callable[[str], None] = print,
) -> dict:
    """Train each task (default: ``BENCHMARK_TASKS``) for ``epochs`` (default: its own) as the module docstring
    says, and print a Markdown table of its memory (``summarize``).  ``sizes`` (n_train, n_val, n_test) are those
    of a dataset to generate (default: ``diffcontact generate``'s).  Returns ``{"header": ..., "rows": [...]}``,
    written after each task to ``out`` (JSON) and beside it with the suffix .md (the table)."""
    names = list(tasks or BENCHMARK_TASKS)
    for name in names:  # (a bad name fails before hours of training)
        load_task(name)
    header = {
        **versions(lightning=lightning.__version__),
        "cpus": os.cpu_count(),
        "threads": threads,
        "load_average_before": list(os.getloadavg()),
        "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }
    lines = [
        f"diffcontact {header['diffcontact']}, torch {header['torch']}, lightning {header['lightning']}, python "
        f"{header['python']}, {header['cpus']} CPUs, {threads} thread(s) per training; default training "
        f"(CM-CD-CLNN) in a fresh process per task; RSS at the end of each epoch; flat: growth after epoch {SETTLE} "
        f"<= {FLAT_MB:.0f} MB; load average before {header['load_average_before'][0]:.2f}",
        "",
        TABLE,
    ]
    echo("\n".join(lines))
    result: dict = {"header": header, "rows": []}
    for name in names:
        generate_dataset(name, data, **(sizes or {}), progress=False, echo=None)
        load = os.getloadavg()[0]
        with worker_pool(1) as pool:
            try:
                run = pool.submit(_train, name, data, epochs, threads).result()
            except BrokenProcessPool as err:
                raise DiffContactError(f"{name}: the training process ended abruptly (out of memory?)") from err
        row = {"task": name, **summarize(run["rss_mb"]), "wall_time_s": run["wall_time_s"]}
        row.update(load_average=[load, os.getloadavg()[0]], rss_mb=run["rss_mb"])
        result["rows"].append(row)
        lines.append(_line(row))
        echo(lines[-1])
        header["load_average_after"] = list(os.getloadavg())
        if out:  # (after each task: a long run interrupted keeps the tasks it finished)
            write_json(out, result)
            write_text(Path(out).with_suffix(".md"), "\n".join(lines) + "\n")
    return result
