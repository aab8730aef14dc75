"""Generate the datasets of a task (spec B): full trajectories from the ground-truth simulator (CM, float64),
one 5-frame chunk per trajectory, optional noise, stored with metadata and checksums (see :mod:`store`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from diffcontact.config import check_array_size
from diffcontact.data.chunking import gather_windows, select_chunks
from diffcontact.data.noise import add_noise, check_noise, noise_kind
from diffcontact.data.store import (
    FORMAT,
    SPLITS,
    config_json,
    describe,
    load_meta,
    remove_stale,
    save_arrays,
    save_meta,
    verify_dataset,
    versions,
)
from diffcontact.errors import ConfigError, DatasetError
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems import build_task
from diffcontact.systems.base import Task

DEFAULT_SIZES = {"train": 800, "val": 100, "test": 100}
DEFAULT_SEEDS = {"train": 0, "val": 1, "test": 2}
_SEGMENT = 10  # frames simulated between progress-bar updates
_CHUNK_STREAM, _NOISE_STREAM = 1, 2


def child_seed(seed: int, stream: int) -> int:
    """An independent 63-bit seed derived from (seed, stream) (numpy SeedSequence), so that the chunk and noise
    draws are not correlated with the initial conditions drawn from ``seed`` itself."""
    return int(np.random.SeedSequence([seed, stream]).generate_state(1, np.uint64)[0]) >> 1


def _check_int(name: str, value: int, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise ConfigError(f"{name} = {value!r} is not an integer >= {lo}")
    return int(value)


def simulate_split(
    task: Task, n: int, seed: int, frames: int, progress: bool = True, label: str = ""
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample ``n`` initial states with ``seed`` and simulate ``frames`` frames (true Params, CM):
    x, v (n, T, P, d) and contact (n, T) bool. The rollout runs in segments only to update the progress bar."""
    sim = simulator_for(task)
    state = task.sample(n, seed)
    xs, vs, cs = [state.x[:, None]], [state.v[:, None]], [torch.zeros(n, 1, dtype=torch.bool)]
    fmt = "{desc}: {percentage:3.0f}%|{bar}| {n}/{total_fmt} trajectories [{elapsed}<{remaining}]"
    with torch.no_grad(), tqdm(total=n, desc=label, bar_format=fmt, disable=not progress, leave=False) as bar:
        done = 1
        while done < frames:
            k = min(_SEGMENT, frames - done)
            x, v, c = sim.rollout(state, task.params, task.dt, k + 1)
            xs.append(x[:, 1:])
            vs.append(v[:, 1:])
            cs.append(c[:, 1:])
            state = State(x[:, -1], v[:, -1])
            done += k
            bar.update(n * (done - 1) // (frames - 1) - bar.n)  # (integers: a float sum overshoots total)
    return torch.cat(xs, 1), torch.cat(vs, 1), torch.cat(cs, 1)


def make_split(
    task: Task,
    n: int,
    seed: int,
    frames: int,
    chunk_len: int = 5,
    p_collision: float = 0.5,
    noise: float = 0.0,
    progress: bool = True,
    label: str = "",
) -> dict[str, np.ndarray]:
    """The arrays of one split (names and shapes in :mod:`diffcontact.data.store`)."""
    x, v, contact = simulate_split(task, n, seed, frames, progress, label)
    starts, chunk_cld = select_chunks(
        contact, chunk_len, torch.Generator().manual_seed(child_seed(seed, _CHUNK_STREAM)), p_collision
    )
    cx, cv = gather_windows(x, starts, chunk_len), gather_windows(v, starts, chunk_len)
    if noise > 0:
        gen = torch.Generator().manual_seed(child_seed(seed, _NOISE_STREAM))
        P, d = x.shape[2:]
        nx, nv = add_noise(task.system, cx.reshape(-1, P, d), cv.reshape(-1, P, d), noise, gen)
        cx, cv = nx.reshape(cx.shape), nv.reshape(cv.shape)
    return {
        "x": x.numpy(),
        "v": v.numpy(),
        "contact": contact.numpy(),
        "t": np.arange(frames, dtype=np.float64) * task.dt,
        "chunk_start": starts.numpy().astype(np.int64),
        "chunk_x": cx.contiguous().numpy(),
        "chunk_v": cv.contiguous().numpy(),
        "chunk_collision": chunk_cld.numpy(),
    }


def _request(task: Task, sizes, seeds, frames, chunk_len, p_collision, noise) -> dict[str, Any]:
    return {
        "task": task.config.name,
        "config": config_json(task.config),
        "sizes": dict(sizes),
        "seeds": dict(seeds),
        "frames": frames,
        "dt": task.dt,
        "chunk_len": chunk_len,
        "p_collision": p_collision,
        "noise": noise,
        "noise_kind": noise_kind(task.system) if noise > 0 else None,
        "dynamics": "lagrangian",
        "contact_model": "CM",
        "dtype": task.config.dtype,
    }


def generate_dataset(
    task: str | Path | Task,
    out: str | Path = "data",
    *,
    n_train: int = DEFAULT_SIZES["train"],
    n_val: int = DEFAULT_SIZES["val"],
    n_test: int = DEFAULT_SIZES["test"],
    seeds: tuple[int, int, int] = (DEFAULT_SEEDS["train"], DEFAULT_SEEDS["val"], DEFAULT_SEEDS["test"]),
    frames: int | None = None,
    chunk_len: int = 5,
    p_collision: float = 0.5,
    noise: float = 0.0,
    force: bool = False,
    progress: bool = True,
    echo: Callable[[str], None] | None = print,
) -> dict[str, Any]:
    """Generate (or reuse) ``<out>/<task>/``: train/val/test trajectories of ``frames`` frames (default: the
    task's), each split from its own seed, one chunk of ``chunk_len`` frames per trajectory, noise ``noise``
    on the chunks. Skipped (and the metadata returned with ``skipped = True``) if an identical, valid dataset
    exists, unless ``force``. ``echo`` receives one summary line per split (None: silent)."""
    task = task if isinstance(task, Task) else build_task(task)
    sizes = {
        "train": _check_int("n_train", n_train, 1),
        "val": _check_int("n_val", n_val, 1),
        "test": _check_int("n_test", n_test, 1),
    }
    seed_map = dict(zip(SPLITS, (_check_int(f"seeds[{i}]", s, 0) for i, s in enumerate(seeds))))
    if len(seeds) != 3 or len(set(seed_map.values())) != 3:
        raise ConfigError(f"seeds = {tuple(seeds)} must be three different seeds (train, val, test)")
    frames = task.frames if frames is None else _check_int("frames", frames, 2)
    chunk_len = _check_int("chunk_len", chunk_len, 2)
    if chunk_len > frames:
        raise ConfigError(f"chunk_len = {chunk_len} is larger than frames = {frames}")
    if not 0.0 < p_collision <= 1.0:
        raise ConfigError(f"p_collision = {p_collision} is not in (0, 1]")
    noise = check_noise(noise)
    coords = task.system.n_points * task.system.d
    check_array_size(f"{max(sizes.values())} trajectories x {frames} frames of {task.config.name}",
                     2 * max(sizes.values()) * frames * coords)  # fmt: skip
    request = _request(task, sizes, seed_map, frames, chunk_len, p_collision, noise)
    folder = Path(out) / task.config.name
    if not force and (folder / "meta.json").is_file():
        try:
            meta = load_meta(folder)
            if meta.get("request") == request:
                meta = verify_dataset(folder, task.config)
                if echo:
                    echo(f"{task.config.name}: an identical, valid dataset exists in {folder}; skipped")
                return {**meta, "skipped": True}
        except DatasetError:
            pass  # invalid or different: regenerate
    remove_stale(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meta: dict[str, Any] = {
        "format": FORMAT,
        "request": request,
        "config_text": task.config.source,
        "versions": versions(),
        "splits": {},
    }
    for split in SPLITS:
        t0 = time.perf_counter()
        n, seed = sizes[split], seed_map[split]
        arrays = make_split(
            task, n, seed, frames, chunk_len, p_collision, noise, progress, f"{task.config.name} {split}"
        )
        digest = save_arrays(folder / f"{split}.npz", arrays)
        seconds = time.perf_counter() - t0
        traj_cld = int(arrays["contact"].any(1).sum())
        chunk_cld = int(arrays["chunk_collision"].sum())
        meta["splits"][split] = {
            "file": f"{split}.npz",
            "sha256": digest,
            "n": n,
            "seed": seed,
            "chunk_seed": child_seed(seed, _CHUNK_STREAM),
            "noise_seed": child_seed(seed, _NOISE_STREAM) if noise > 0 else None,
            "arrays": describe(arrays),
            "trajectories_with_collision": traj_cld,
            "chunks_with_collision": chunk_cld,
            "collision_frames": int(arrays["contact"].sum()),
            "seconds": round(seconds, 3),
        }
        if echo:
            echo(
                f"{task.config.name} {split}: {n} trajectories x {frames} frames, {traj_cld} with a collision; "
                f"{n} chunks of {chunk_len}, {chunk_cld} with a collision ({chunk_cld / n:.1%}); {seconds:.1f} s"
            )
    save_meta(folder, meta)
    return {**meta, "skipped": False}
