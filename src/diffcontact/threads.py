"""One thread setting for torch, numba and the contact solver's pool; waiting threads that do not spin.

- :func:`available_cpus`: the CPUs this process may really use: its affinity mask and, if the container limits it,
  the cgroup CPU quota (``/sys/fs/cgroup/cpu.max``, v2; ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``, v1).
- :func:`set_threads`: one number for torch's intra-op threads, numba's threads and the solver's thread pool (sized
  from ``numba.get_num_threads()``, ``solver/kernel.py``).
- :func:`quiet_waiting_env`: ``OMP_WAIT_POLICY=PASSIVE`` and ``KMP_BLOCKTIME=0`` unless the user set them, so that
  OpenMP workers sleep instead of spinning between parallel regions (spinning workers made a training step 30×
  slower beside two busy processes).  The OpenMP runtime reads them when it is loaded, i.e. at ``import torch``:
  ``diffcontact/__init__.py`` calls it before importing torch.  A program that imports torch before diffcontact
  must set them itself: :func:`spin_warning` says so when it did not.

This module imports neither torch nor numba at import time (it runs before them).
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterator, MutableMapping
from contextlib import contextmanager
from pathlib import Path

QUIET_ENV = {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}
CGROUP_V2 = Path("/sys/fs/cgroup/cpu.max")
CGROUP_V1 = Path("/sys/fs/cgroup/cpu")


def quiet_waiting_env(environ: MutableMapping[str, str] | None = None) -> dict[str, str]:
    """Set :data:`QUIET_ENV` in ``environ`` (default ``os.environ``) where not set; returns what was set."""
    environ = os.environ if environ is None else environ
    added = {k: v for k, v in QUIET_ENV.items() if k not in environ}
    environ.update(added)
    return added


def spin_warning(environ: MutableMapping[str, str] | None = None, modules: dict | None = None) -> str | None:
    """The warning for a process that loaded torch before ``import diffcontact`` without choosing a wait policy, with
    torch using more than one thread: its OpenMP runtime read ``OMP_WAIT_POLICY`` when torch loaded, found none, and
    its workers spin while they wait (beside the solver's threads, and beside other processes on a shared machine).
    None otherwise.  ``environ``, ``modules``: default ``os.environ``, ``sys.modules``."""
    environ = os.environ if environ is None else environ
    torch = (sys.modules if modules is None else modules).get("torch")
    threads = getattr(torch, "get_num_threads", None)
    if threads is None or "OMP_WAIT_POLICY" in environ or threads() <= 1:
        return None
    return (
        "torch was imported before diffcontact, so its OpenMP threads spin while they wait (OMP_WAIT_POLICY is read "
        "once, when torch loads): the contact solver ran 1.1-1.5x slower beside them on an idle 2-core machine, and a "
        "training step can be many times slower on a shared one. Import diffcontact before torch, or start Python "
        "with OMP_WAIT_POLICY=PASSIVE set (OMP_WAIT_POLICY=ACTIVE keeps the spinning and silences this warning)."
    )


def cgroup_cpu_limit(v2: Path = CGROUP_V2, v1: Path = CGROUP_V1) -> float | None:
    """The cgroup CPU quota in CPUs (quota / period, e.g. 1.5), or None if there is none or no file to read.

    v2: ``cpu.max`` holds "QUOTA PERIOD" in µs, QUOTA "max" for no limit; v1: ``cpu.cfs_quota_us`` (−1 for no limit)
    and ``cpu.cfs_period_us`` in the folder ``v1``."""
    try:
        quota, period = v2.read_text().split()[:2]
    except (OSError, ValueError):
        try:
            quota, period = (v1 / "cpu.cfs_quota_us").read_text().strip(), (v1 / "cpu.cfs_period_us").read_text()
        except OSError:
            return None
    if quota.strip() in ("max", "-1"):
        return None
    try:
        q, p = float(quota), float(period)
    except ValueError:
        return None
    return q / p if q > 0 and p > 0 else None


def available_cpus(affinity: set[int] | None = None, quota: float | None = None, *, read_cgroup: bool = True) -> int:
    """CPUs available to this process (≥ 1): the size of its affinity mask (``os.sched_getaffinity``, else
    ``os.cpu_count()``), lowered to the cgroup quota rounded up (:func:`cgroup_cpu_limit`) if there is one.

    ``affinity`` and ``quota`` replace what is read from the system (tests); ``read_cgroup`` False ignores cgroups."""
    if affinity is None:
        try:
            affinity = os.sched_getaffinity(0)
        except AttributeError:  # (not on Linux)
            affinity = set(range(os.cpu_count() or 1))
    n = max(1, len(affinity))
    if quota is None and read_cgroup:
        quota = cgroup_cpu_limit()
    if quota is not None:
        n = min(n, max(1, math.ceil(quota)))
    return n


JOB_MEMORY = 1.5e9  # bytes a training run's process may need (measured: 0.6 GB resident for the benchmark's tasks)


def available_memory(meminfo: Path = Path("/proc/meminfo")) -> float | None:
    """The memory available to new processes in bytes (``MemAvailable`` of /proc/meminfo), or None if unknown."""
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def default_jobs(cpus: int | None = None, memory: float | None = None) -> int:
    """Processes to run at once (≥ 1): one per available CPU (:func:`available_cpus`), fewer if the available memory
    (:func:`available_memory`) holds fewer than :data:`JOB_MEMORY` each."""
    cpus = available_cpus() if cpus is None else cpus
    memory = available_memory() if memory is None else memory
    return max(1, min(cpus, int(memory // JOB_MEMORY))) if memory is not None else max(1, cpus)


def set_threads(threads: int | None = None) -> int:
    """Use ``threads`` threads (None: :func:`available_cpus`) in torch, numba and the solver's pool; returns it.

    numba cannot use more threads than ``NUMBA_NUM_THREADS`` (default: the machine's CPUs), so the solver's pool is
    capped there."""
    import numba
    import torch

    if threads is None:
        threads = available_cpus()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        from diffcontact.errors import ConfigError

        raise ConfigError(f"threads = {threads!r} is not an integer >= 1")
    torch.set_num_threads(threads)
    # (numba.config, numba's documented name, is set up at run time: its typing knows neither it nor its attributes)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))  # pyright: ignore[reportPrivateImportUsage, reportAttributeAccessIssue]
    return threads


@contextmanager
def one_thread() -> Iterator[None]:
    """torch, and MKL's LAPACK under it, on one thread inside the block.  For the batched small-matrix LAPACK calls of
    the physics path (least squares of 20-400 contacts): with waiting threads that sleep (:data:`QUIET_ENV`) every
    one of their many small parallel regions wakes the others, and on 2 threads they ran 1.6-3.4× slower than on one
    (a 50-node rope's data generated 3.3× slower, half of it system time)."""
    import torch

    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def thread_env(threads: int, environ: MutableMapping[str, str] | None = None) -> dict[str, str]:
    """The environment of a child process that should use ``threads`` threads (torch, numba, the solver's pool) and
    quiet waiting (the user's own wait settings kept): a copy of ``environ`` (default ``os.environ``)."""
    env = dict(os.environ if environ is None else environ)
    env.update(OMP_NUM_THREADS=str(threads), NUMBA_NUM_THREADS=str(threads))
    quiet_waiting_env(env)
    return env
