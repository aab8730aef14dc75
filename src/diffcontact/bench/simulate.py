"""Simulation benchmark: wall time of N trajectories x T frames per task (Algorithm 1, CM, float64)."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import torch

import diffcontact
from diffcontact.bench import check_counts
from diffcontact.config import available_tasks
from diffcontact.errors import ConfigError
from diffcontact.files import write_text
from diffcontact.simulator import simulator_for
from diffcontact.solver import ContactSolver
from diffcontact.systems import BENCHMARK_TASKS, build_task


def run_simulation_benchmark(
    tasks=None,
    n: int = 1000,
    steps: int = 100,
    threads: int = 2,
    seed: int = 0,
    warmup_steps: int = 5,
    out: str | None = None,
) -> list[dict]:
    """Time each task's rollout (after a short warm-up rollout, excluded) and print a Markdown table.

    Columns: initial-state sampling time, rollout time, ms per step, fraction of (trajectory, frame) pairs in
    contact, solver calls and solver failures (problems not converged; the benchmark continues with
    on_failure="count", which gives those contacts zero impulse, and reports the count). Returns the rows.
    """
    names = list(tasks or BENCHMARK_TASKS)
    check_counts(n=n, threads=threads, warmup_steps=warmup_steps)
    check_counts(2, steps=steps)
    unknown = [name for name in names if name not in available_tasks() and not Path(name).is_file()]
    if unknown:
        raise ConfigError(f"tasks {unknown} are unknown; available: {', '.join(available_tasks())}")
    torch.set_num_threads(threads)
    print(
        f"diffcontact {diffcontact.__version__}, torch {torch.__version__}, python {platform.python_version()}, "
        f"{platform.machine()}, {os.cpu_count()} CPUs, {torch.get_num_threads()} torch threads; "
        f"N = {n} trajectories x T = {steps} frames, float64, exact contact model (CM)"
    )
    header = "| task | sample (s) | simulate (s) | ms / step | frames in contact | solver calls | solver failures |"
    lines = [header, "|---|---|---|---|---|---|---|"]
    print(header)
    rows, total = [], 0.0
    for name in names:
        task = build_task(name)
        solver = ContactSolver(on_failure="count")
        sim = simulator_for(task, solver=solver)
        t0 = time.perf_counter()
        state = task.sample(n, seed)
        t_sample = time.perf_counter() - t0
        with torch.no_grad():
            sim.rollout(state, task.params, task.dt, warmup_steps)  # warm-up, excluded
            solver.reset()
            t0 = time.perf_counter()
            _, _, hit = sim.rollout(state, task.params, task.dt, steps)
            t_sim = time.perf_counter() - t0
        total += t_sim
        row = {
            "task": name,
            "sample_s": t_sample,
            "simulate_s": t_sim,
            "ms_per_step": 1e3 * t_sim / (steps - 1),
            "contact_fraction": hit[:, 1:].float().mean().item(),
            "solver_calls": solver.calls,
            "solver_failures": solver.failures,
        }
        rows.append(row)
        line = (
            f"| {name} | {t_sample:.2f} | {t_sim:.1f} | {row['ms_per_step']:.0f} | "
            f"{row['contact_fraction']:.1%} | {solver.calls} | {solver.failures} |"
        )
        lines.append(line)
        print(line, flush=True)
    last = f"| all {len(names)} | | {total:.1f} | | | | {sum(r['solver_failures'] for r in rows)} |"
    lines.append(last)
    print(last)
    if out:
        write_text(out, "\n".join(lines) + "\n")
    return rows
