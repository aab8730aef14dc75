"""``diffcontact simulate``: trajectories of a task with its true Params, written to one .npz (and a GIF)."""

from __future__ import annotations

import json

import numpy as np
import torch

from diffcontact.config import check_array_size
from diffcontact.errors import ConfigError
from diffcontact.files import check_output, save_npz, versions
from diffcontact.simulator import simulator_for
from diffcontact.systems import build_task


def simulate_task(
    task_name: str, n: int, steps: int | None, seed: int, out: str, gif: str | None = None, dynamics: str = "lagrangian"
) -> dict:
    """Simulate ``n`` trajectories of a task with its true Params (CM, float64) and write ``out`` (.npz).

    The file holds x, v (N, T, P, d), t (T,) in s, energy (N, T) in J, contact (N, T) bool, the task file's
    text (``config``) and ``meta`` (JSON: versions, seed, dt, command arguments); it is written atomically.
    ``steps`` is the number of frames T (default: the task's ``frames``). Returns meta.
    """
    task = build_task(task_name)
    frames = task.frames if steps is None else steps
    check_output(out, "--out")
    if gif:
        check_output(gif, "--gif")
    if n < 1:
        raise ConfigError(f"n = {n} is not >= 1")
    if frames < 2:
        raise ConfigError(f"steps = {frames} is not >= 2")
    coords = task.system.n_points * task.system.d
    check_array_size(f"{n} trajectories x {frames} frames of {task.config.name}", 2 * n * frames * coords)
    sim = simulator_for(task, dynamics=dynamics)
    state = task.sample(n, seed)
    with torch.no_grad():
        x, v, hit = sim.rollout(state, task.params, task.dt, frames)
        energy = task.system.energy(task.params, x.flatten(0, 1), v.flatten(0, 1)).reshape(n, frames)
    meta = {
        "task": task.config.name,
        "n": n,
        "frames": frames,
        "seed": seed,
        "dt": task.dt,
        "dynamics": dynamics,
        "contact_model": "CM",
        "dtype": task.config.dtype,
        **versions(),
    }
    save_npz(
        out,
        x=x.numpy(),
        v=v.numpy(),
        t=np.arange(frames) * task.dt,
        energy=energy.numpy(),
        contact=hit.numpy(),
        config=np.array(task.config.source),
        meta=np.array(json.dumps(meta)),
    )
    if gif:
        from diffcontact.render import render_gif

        render_gif(task.system, x[0].numpy(), hit[0].numpy(), gif, task.dt)
    return meta
