"""Training-step benchmark: the time of one training step per task and model, split into its parts.

A step is what ``ContactLightningModule.training_step`` does in ``diffcontact train`` with its defaults: the model and
settings of the task's default training (``TrainConfig.resolve``: the task file's potential, for example) and, unless
given, its batch (50 chunks with the default preset; the published preset's is 200).  It is the loss of a batch of
5-frame chunks (forward), its backward pass, and the optimiser (AdamW, the finiteness check, the projection of μ and
e).  It is timed twice side by side, alternating: as is, and with contacts disabled (the same model and parameters,
a detector that finds none).  The parts are

- dynamics: forward + backward without contacts (the Lagrangian or Hamiltonian field, ∇V of the potential network,
  RK4, the loss);
- contact model: forward + backward with contacts minus without (detection, effective mass, both solves and their
  backward); "contact fwd" is its forward part measured directly;
- optimiser.

A step without contacts that takes longer than the step with them (which does that work and more) marks a disturbed
measurement: the row is flagged (``disturbed``), its contact shares are printed as "–" and a note after the table
names it, instead of a share of 0.

Wall times suffer most from other processes on a shared machine; the process's CPU time of the step (all its
threads) much less, so the table also gives the step's CPU time and the contact model's share of it (CPU time with
contacts minus without, over with).

The data are a small synthetic split of the task made as the datasets are (``data.generate.make_split``: the task's
own simulator, CM, float64, one chunk per trajectory, about half of them colliding), in float32 as in training.
With ``busy`` > 0, the benchmark also starts that many busy processes itself and times the step with them running
and paused (SIGSTOP), alternating, and reports the slowdown; it stops them before returning.
"""

from __future__ import annotations

import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

import diffcontact
from diffcontact.data.generate import make_split
from diffcontact.errors import ConfigError
from diffcontact.files import atomic_write
from diffcontact.models import ALL_MODELS, BASELINE_NAMES, ContactModelNet
from diffcontact.systems import BENCHMARK_TASKS, build_task
from diffcontact.train.config import TrainConfig
from diffcontact.train.module import ContactLightningModule

# a CPU-bound loop that dies with the benchmark, even if that is killed outright (Linux PR_SET_PDEATHSIG = 1, SIGKILL)
BUSY_LOOP = """
import ctypes, os, sys
if sys.platform == "linux":
    ctypes.CDLL(None).prctl(1, 9)
if os.getppid() != int(sys.argv[1]):
    sys.exit()
print("ready", flush=True)
while True:
    pass
"""


class NoContacts:
    """A detector that finds no contact: the model with contacts disabled."""

    def detect(self, x: torch.Tensor) -> None:
        return None


@dataclass
class TimedContacts:
    """A contact model that adds the wall time of its forward calls to ``seconds``."""

    model: Callable[..., Any]
    seconds: float = 0.0

    def __call__(self, *args, **kwargs):
        t0 = time.perf_counter()
        out = self.model(*args, **kwargs)
        self.seconds += time.perf_counter() - t0
        return out


class StepTimer:
    """One model's training step on one batch, timed by part; ``contacts`` False disables them (the same params)."""

    def __init__(self, task: str, model: str, batch: tuple[torch.Tensor, ...], seed: int = 0):
        self.module = ContactLightningModule(TrainConfig.resolve(task, model, seed=seed, dtype="float32"))
        self.batch = batch
        opt = self.module.configure_optimizers()
        self.opt = opt["optimizer"] if isinstance(opt, dict) else opt
        self.net = self.module.net
        self.baseline = self.module.baseline
        if not self.baseline:
            sim = self._contact_net().simulator
            self.timed = TimedContacts(sim.contact_model)
            self.sims = {
                True: replace(sim, contact_model=self.timed),
                False: replace(sim, system=replace(sim.system, detector=NoContacts())),
            }

    def _contact_net(self) -> ContactModelNet:
        """The model's net, a contact model's (not a baseline's)."""
        if not isinstance(self.net, ContactModelNet):
            raise TypeError(f"{self.module.config.model} is not a contact model (ContactModelNet)")
        return self.net

    def step(self, contacts: bool = True) -> dict[str, float]:
        """One training step; returns its parts' wall times in s (forward, backward, optimiser, contact_fwd) and
        the CPU time of the process (``cpu``, all threads: less sensitive to other processes than wall time)."""
        if not self.baseline:
            self._contact_net().simulator = self.sims[contacts]
            self.timed.seconds = 0.0
        c0, t0 = time.process_time(), time.perf_counter()
        loss = self.module.loss(self.batch)
        t1 = time.perf_counter()
        self.opt.zero_grad()
        loss.backward()
        t2 = time.perf_counter()
        grads = [p.grad for p in self.net.parameters() if p.grad is not None]
        if all(bool(torch.isfinite(g).all()) for g in grads) and bool(torch.isfinite(loss)):
            self.opt.step()
            learned = self.module.learned
            if self.module.learns_contacts and learned is not None:
                learned.project_()
        t3, c3 = time.perf_counter(), time.process_time()
        contact_fwd = self.timed.seconds if not self.baseline and contacts else 0.0
        parts = {"forward": t1 - t0, "backward": t2 - t1, "optimiser": t3 - t2, "contact_fwd": contact_fwd}
        return {**parts, "cpu": c3 - c0}


def synthetic_batch(task_name: str, model: str, batch: int, seed: int = 0) -> tuple[tuple[torch.Tensor, ...], float]:
    """A batch of ``batch`` 5-frame chunks of the task in float32 (a baseline's one-step pairs: the first two frames)
    made by ``make_split``; returns it and the fraction of colliding chunks."""
    task = build_task(task_name)
    arrays = make_split(task, batch, seed, task.frames, progress=False)
    x = torch.from_numpy(arrays["chunk_x"]).float()
    v = torch.from_numpy(arrays["chunk_v"]).float()
    colliding = float(arrays["chunk_collision"].mean())
    if model in BASELINE_NAMES:
        return (x[:, 0], v[:, 0], x[:, 1], v[:, 1]), colliding
    return (x, v), colliding


def _median(samples: list[dict[str, float]], key: str) -> float:
    return statistics.median(s[key] for s in samples)


def _step(samples: list[dict[str, float]], parts=("forward", "backward", "optimiser")) -> float:
    """The median over samples of the sum of ``parts``."""
    return statistics.median(sum(s[k] for k in parts) for s in samples)


def start_busy(n: int) -> list[subprocess.Popen]:
    """Start ``n`` processes that spin a CPU each (a pure-Python busy loop; they die with this process)."""
    procs = [
        subprocess.Popen([sys.executable, "-c", BUSY_LOOP, str(os.getpid())], stdout=subprocess.PIPE, text=True)
        for _ in range(n)
    ]
    for p in procs:  # (ready: tied to this process, and spinning)
        if p.stdout is None:
            raise RuntimeError("a busy process has no stdout pipe")
        p.stdout.readline()
    return procs


def signal_all(procs: list[subprocess.Popen], sig: int) -> None:
    for p in procs:
        p.send_signal(sig)


def stop_busy(procs: list[subprocess.Popen]) -> None:
    """Stop the busy processes started by :func:`start_busy` (resumed first, then killed and waited for)."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGCONT)
            p.kill()
        p.wait()
        if p.stdout is not None:
            p.stdout.close()


def time_model(timer: StepTimer, warmup: int, repeats: int, busy: list[subprocess.Popen]) -> dict:
    """Medians over ``repeats`` (after ``warmup``) of the step with contacts and without, alternating; with busy
    processes, also of the step while they run (they are paused, SIGSTOP, for the other measurements)."""
    full, bare, loaded = [], [], []
    for r in range(warmup + repeats):
        signal_all(busy, signal.SIGSTOP)
        a = timer.step(True)
        b = timer.step(False) if not timer.baseline else None
        c = None
        if busy:
            signal_all(busy, signal.SIGCONT)
            time.sleep(0.05)  # (let them take the CPUs)
            c = timer.step(True)
        if r >= warmup:
            full.append(a)
            if b is not None:
                bare.append(b)
            if c is not None:
                loaded.append(c)
    signal_all(busy, signal.SIGSTOP)
    row = {k: _median(full, k) for k in ("forward", "backward", "optimiser", "contact_fwd", "cpu")}
    row["step"] = _step(full)
    if bare:
        fb_bare = _step(bare, ("forward", "backward"))
        row["step_no_contacts"] = _step(bare)
        row["cpu_no_contacts"] = _median(bare, "cpu")
        row["contact_share_cpu"] = max(row["cpu"] - row["cpu_no_contacts"], 0.0) / row["cpu"]
        row["dynamics"] = fb_bare
        contact = _step(full, ("forward", "backward")) - fb_bare
        row["contact"] = max(contact, 0.0)
        row["contact_share"] = row["contact"] / row["step"]
        # the step without contacts slower than with them: impossible for the work done, so a disturbed measurement
        # (reported, not hidden behind a share of 0)
        row["disturbed"] = contact < 0 or row["cpu"] < row["cpu_no_contacts"]
    if loaded:
        row["step_busy"] = _step(loaded)
        row["busy_ratio"] = row["step_busy"] / row["step"]
    return row


def _ms(x: float | None) -> str:
    return "–" if x is None else f"{1e3 * x:.1f}"


def run_train_benchmark(
    tasks=None,
    models=("CM-CD-CLNN",),
    batch: int | None = None,
    warmup: int = 2,
    repeats: int = 15,
    seed: int = 0,
    busy: int = 0,
    out: str | None = None,
    echo=print,
) -> dict:
    """Time a training step per task and model (see the module docstring) on ``batch`` chunks (None: the task's
    training batch); print a Markdown table and return ``{"header": ..., "rows": [...]}`` (times in s), also written
    as JSON to ``out`` if given."""
    names = list(tasks or BENCHMARK_TASKS)
    for m in models:
        if m not in ALL_MODELS:
            raise ConfigError(f"model = {m!r} is not one of {list(ALL_MODELS)}")
    for name, value, lo in (("batch", batch, 1), ("repeats", repeats, 1), ("warmup", warmup, 0), ("busy", busy, 0)):
        if value is not None and value < lo:
            raise ConfigError(f"{name} = {value} is not >= {lo}")
    import numba

    header = {
        "diffcontact": diffcontact.__version__,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "numba_threads": numba.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", ""),
        "batch": batch,
        "warmup": warmup,
        "repeats": repeats,
        "busy": busy,
        "load_average_before": list(os.getloadavg()),
        "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }
    echo(
        f"diffcontact {header['diffcontact']}, torch {header['torch']}, python {header['python']}, "
        f"{header['machine']}, {header['cpus']} CPUs, {header['torch_threads']} torch / {header['numba_threads']} "
        f"solver threads, OMP_WAIT_POLICY={header['omp_wait_policy'] or 'unset'}; "
        f"{batch or 'the training batch of'} chunks of 5 frames, "
        f"float32; medians of {repeats} steps after {warmup}; load average {header['load_average_before'][0]:.2f}"
    )
    cols = "| task | model | chunks | colliding | step (ms) | step CPU | dynamics | contact | optimiser "
    cols += "| contact share | step without contacts | contact fwd (measured) | contact share (CPU) |"
    if busy:
        cols += f" step beside {busy} busy | slowdown |"
    echo(cols)
    echo("|" + "---|" * (cols.count("|") - 1))
    rows, disturbed = [], []
    procs = start_busy(busy) if busy else []
    try:
        signal_all(procs, signal.SIGSTOP)
        for name in names:
            for model in models:
                chunks = batch or TrainConfig.resolve(name, model).batch_size
                data, colliding = synthetic_batch(name, model, chunks, seed)
                timer = StepTimer(name, model, data, seed)
                row = {"task": name, "model": model, "batch": chunks, "colliding": colliding}
                row.update(time_model(timer, warmup, repeats, procs))
                rows.append(row)
                line = (
                    f"| {name} | {model} | {chunks} | {colliding:.0%} | {_ms(row['step'])} | {_ms(row['cpu'])} | "
                    f"{_ms(row.get('dynamics'))} | "
                    f"{_ms(row.get('contact'))} | {_ms(row['optimiser'])} | "
                    + ("–" if "contact_share" not in row or row["disturbed"] else f"{row['contact_share']:.0%}")
                    + f" | {_ms(row.get('step_no_contacts'))} | "
                    + f"{_ms(None if timer.baseline else row['contact_fwd'])} | "
                    + ("–" if "contact_share_cpu" not in row or row["disturbed"] else f"{row['contact_share_cpu']:.0%}")
                    + " |"
                )
                if busy:
                    line += f" {_ms(row['step_busy'])} | {row['busy_ratio']:.2f}× |"
                echo(line)
                if row.get("disturbed"):
                    disturbed.append(
                        f"{name} {model}: the step without contacts ({_ms(row['step_no_contacts'])} ms) took longer "
                        f"than the step with them ({_ms(row['step'])} ms), a disturbed measurement: its contact "
                        "share is not reported (–); run the benchmark again for that row"
                    )
    finally:
        stop_busy(procs)
    for note in disturbed:
        echo(note)
    header["load_average_after"] = list(os.getloadavg())
    echo(f"load average after: {header['load_average_after'][0]:.2f}")
    result = {"header": header, "rows": rows}
    if out:
        atomic_write(Path(out), lambda fh: fh.write((json.dumps(result, indent=2) + "\n").encode()))
    return result
