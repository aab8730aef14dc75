"""Generate the datasets of a task (as published): full trajectories from the ground-truth simulator (CM, float64),
one 5-frame chunk per trajectory, optional noise, stored with metadata and checksums (see :mod:`store`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from diffcontact.config import check_array_size
from diffcontact.data.chunking import gather_windows, select_chunks
from diffcontact.data.noise import add_noise, check_noise, noise_kind
from diffcontact.data.store import FORMAT, SPLITS, config_json, describe, load_meta, load_split, remove_stale, save_meta
from diffcontact.errors import ConfigError, DatasetError, DiffContactError
from diffcontact.files import save_arrays, versions
from diffcontact.lock import output_lock
from diffcontact.simulator import simulator_for
from diffcontact.state import State
from diffcontact.systems import build_task
from diffcontact.systems.base import Task

DEFAULT_SIZES = {"train": 800, "val": 100, "test": 100}
DEFAULT_SEEDS = {"train": 0, "val": 1, "test": 2}
_SEGMENT = 10  # frames simulated between progress-bar updates
BLOCK = 256  # trajectories simulated in one batch at most: the unit of work of a worker (``simulate_split``)
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
    task: Task,
    n: int,
    seed: int,
    frames: int,
    progress: bool = True,
    label: str = "",
    workers: int = 1,
    pool: Executor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample ``n`` initial states with ``seed`` and simulate ``frames`` frames (true Params, CM):
    x, v (n, T, P, d) and contact (n, T) bool.

    The trajectories are simulated in blocks of at most ``BLOCK`` (``blocks``: fixed by n alone), one after the other
    or, with ``workers`` > 1, in that many processes (of ``pool``, default a new ``worker_pool``).  A trajectory's
    initial state is drawn here whatever the workers, and its simulation depends on its block only (the solver's
    results can depend on the other problems of its batch in the last bits), so the arrays are the same to the
    bit for any number of workers.
    """
    state = task.sample(n, seed)
    workers = _check_int("workers", workers, 1)
    bounds = blocks(n)
    out: list[torch.Tensor] = []  # (x, v, contact of all n, filled block by block: no second copy of the split)

    def put(a: int, part) -> None:
        if not out:
            out.extend(torch.empty((n, *t.shape[1:]), dtype=t.dtype) for t in part)
        for whole, t in zip(out, part):
            whole[a : a + len(t)] = t

    fmt = "{desc}: {percentage:3.0f}%|{bar}| {n}/{total_fmt} trajectories [{elapsed}<{remaining}]"
    with tqdm(total=n, desc=label, bar_format=fmt, disable=not progress, leave=False) as bar:
        if workers == 1 or len(bounds) == 2:
            for a, b in zip(bounds[:-1], bounds[1:]):
                put(a, _simulate(task, State(state.x[a:b], state.v[a:b]), frames, bar))
        elif pool is None:
            with worker_pool(workers) as own:
                return simulate_split(task, n, seed, frames, progress, label, workers, own)
        else:
            threads = max(1, torch.get_num_threads() // workers)
            futures: list = [
                pool.submit(_simulate_block, task.config, state.x[a:b].numpy(), state.v[a:b].numpy(), frames, threads)
                for a, b in zip(bounds[:-1], bounds[1:])
            ]
            for future in futures:
                future.add_done_callback(lambda f: bar.update(len(f.result()[0])) if not f.exception() else None)
            try:
                for i, a in enumerate(bounds[:-1]):
                    put(a, [torch.from_numpy(arr) for arr in futures[i].result()])
                    futures[i] = None  # (its arrays, now copied, can go)
            except BrokenProcessPool as err:
                raise DiffContactError(f"{label}: a worker process ended abruptly (killed? out of memory?)") from err
    x, v, c = out
    return x, v, c


def blocks(n: int) -> list[int]:
    """The bounds of the blocks of ``n`` trajectories: ceil(n / BLOCK) blocks of sizes differing by at most one."""
    count = -(-n // BLOCK)
    return np.linspace(0, n, count + 1).round().astype(int).tolist()


def worker_pool(workers: int) -> Executor:
    """A pool of ``workers`` processes for ``simulate_split`` (started by spawning: no fork of a process whose
    torch threads are running)."""
    import multiprocessing

    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))


def _simulate_block(config, x: np.ndarray, v: np.ndarray, frames: int, threads: int):
    """In a worker process: the task rebuilt from its config, ``frames`` frames from the states (x, v) as arrays."""
    torch.set_num_threads(threads)
    task = build_task(config)
    xs, vs, cs = _simulate(task, State(torch.from_numpy(x), torch.from_numpy(v)), frames, None)
    return xs.numpy(), vs.numpy(), cs.numpy()


def _simulate(
    task: Task, state: State, frames: int, bar: tqdm | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``frames`` frames from ``state`` (frame 0), in segments only to move ``bar`` (by this block's trajectories)."""
    sim = simulator_for(task)
    n, start = state.batch, bar.n if bar is not None else 0
    xs, vs, cs = [state.x[:, None]], [state.v[:, None]], [torch.zeros(n, 1, dtype=torch.bool)]
    with torch.no_grad():
        done = 1
        while done < frames:
            k = min(_SEGMENT, frames - done)
            x, v, c = sim.rollout(state, task.params, task.dt, k + 1)
            xs.append(x[:, 1:])
            vs.append(v[:, 1:])
            cs.append(c[:, 1:])
            state = State(x[:, -1], v[:, -1])
            done += k
            if bar is not None:  # (integers: a float sum overshoots total)
                bar.update(start + n * (done - 1) // (frames - 1) - bar.n)
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
    workers: int = 1,
    pool: Executor | None = None,
) -> dict[str, np.ndarray]:
    """The arrays of one split (names and shapes in :mod:`diffcontact.data.store`), simulated in ``workers``
    processes (of ``pool``; the same arrays for any number: ``simulate_split``)."""
    x, v, contact = simulate_split(task, n, seed, frames, progress, label, workers, pool)
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
    workers: int = 1,
) -> dict[str, Any]:
    """Generate (or reuse) ``<out>/<task>/``: train/val/test trajectories of ``frames`` frames (default: the
    task's), each split from its own seed, one chunk of ``chunk_len`` frames per trajectory, noise ``noise``
    on the chunks, simulated in ``workers`` processes (the same bytes for any number).  Skipped (and the metadata
    returned with ``skipped = True``) if an identical dataset exists that loads (metadata, checksums), unless
    ``force``; a complete dataset of another request (other sizes, seeds, ...) is replaced only with ``force``
    (ConfigError otherwise).  The folder is locked while it is written (``diffcontact.lock``: LockError if another
    process writes it).  ``echo`` receives one summary line per split (None: silent)."""
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
    workers = _check_int("workers", workers, 1)
    folder = Path(out) / task.config.name
    with output_lock(folder):
        return _generate_into(folder, task, request, sizes, seed_map, frames, chunk_len, p_collision, noise,
                              force, progress, echo, workers)  # fmt: skip


def _differences(old: dict, new: dict, prefix: str = "") -> str:
    """The entries that differ between two requests, as "sizes.train 800 -> 16, ..." (the config by name only)."""
    out = []
    for key in sorted({*old, *new}):
        a, b = old.get(key), new.get(key)
        if a == b:
            continue
        if key == "config":
            out.append(f"{prefix}config (the task file changed)")
        elif isinstance(a, dict) and isinstance(b, dict):
            out.append(_differences(a, b, f"{prefix}{key}."))
        else:
            out.append(f"{prefix}{key} {a!r} -> {b!r}")
    return ", ".join(out)


def _generate_into(
    folder: Path,
    task: Task,
    request,
    sizes,
    seed_map,
    frames,
    chunk_len,
    p_collision,
    noise,
    force,
    progress,
    echo,
    workers,
) -> dict[str, Any]:
    """generate_dataset's work, under the folder's lock."""
    if not force and (folder / "meta.json").is_file():
        try:
            old: dict[str, Any] | None = load_meta(folder)
        except DatasetError:
            old = None  # (incomplete or unreadable: regenerated)
        if old is not None and old["request"] != request:
            raise ConfigError(
                f"{folder} holds a dataset of another request ({_differences(old['request'], request)}); replace it "
                "with --force (force=True), or generate into another --out"
            )
        try:
            if old is not None:
                for split in SPLITS:  # (as strong as loading: config, checksum, the arrays as recorded)
                    load_split(folder, split, task.config)
                if echo:
                    echo(f"{task.config.name}: an identical, valid dataset exists in {folder}; skipped")
                return {**old, "skipped": True}
        except DatasetError:
            pass  # invalid: regenerated
    remove_stale(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meta: dict[str, Any] = {
        "format": FORMAT,
        "request": request,
        "config_text": task.config.source,
        "versions": versions(),
        "simulation_block": BLOCK,  # (trajectories simulated in one batch at most: simulate_split)
        "splits": {},
    }
    with worker_pool(workers) if workers > 1 else nullcontext() as pool:
        for split in SPLITS:
            _write_split(folder, meta, task, split, sizes[split], seed_map[split], frames, chunk_len, p_collision,
                         noise, progress, echo, workers, pool)  # fmt: skip
    save_meta(folder, meta)
    return {**meta, "skipped": False}


def _write_split(
    folder, meta, task, split, n, seed, frames, chunk_len, p_collision, noise, progress, echo, workers, pool
) -> None:
    """Simulate one split, write its file and record it in ``meta``."""
    t0 = time.perf_counter()
    arrays = make_split(
        task, n, seed, frames, chunk_len, p_collision, noise, progress, f"{task.config.name} {split}", workers, pool
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
