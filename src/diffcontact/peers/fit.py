"""Fit an engine's contact parameters to the training tosses with CMA-ES, then score it on the test tosses.

Optimiser: CMA-ES (the ``cma`` package): the standard derivative-free method for a handful (4-9) of continuous
parameters, robust to the rough, discontinuous landscape that contacts give; one small dependency (numpy only) and
seeded. It searches the fraction u in [0, 1] of each parameter's range (a log range for scale parameters,
``cube.Param``), first from the nominal values (the middle of the range for a parameter without one), with step
0.25, then restarted from random points with twice the population each time (IPOP-CMA-ES) until the budget is
spent: one run settles in one basin of that landscape, and a fit of MuJoCo or Bullet from the nominal values
alone was worse on its own training tosses than the parameters fitted on other tosses (docs/real_data.md).
A generation's candidates are scored in ``jobs`` worker processes at once (``diffcontact peers fit``: one per CPU),
with the same result as in one process.
The fitted set is the engine's ``PARAMETERS`` and, unless ``run_fit(centre_of_mass=False)``, the centre of mass's
offset from the box centre (``cube.COM_PARAMETERS``: com_x, com_y, com_z in m, body frame, from 0), as our models
learn it: with it Bullet's fit scores 10.29 % on the test tosses, without it 13.43 % (docs/results.md).

Objective (minimised, in % of the cube's width): position_error_pct + ROTATION_WEIGHT · rotation_error_deg on the
training tosses (all of them at every evaluation), from the same ``box_toss_metrics`` as the test. ROTATION_WEIGHT
turns the angle into the arc it moves a face centre through, in % of the width: (100 · h θ / 2h) per rad. A rollout
that is not finite scores FAILED.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from importlib import metadata
from pathlib import Path

import numpy as np

from diffcontact.data.measured import with_first_states
from diffcontact.data.tosses import Tosses, read_tosses, resting_table_height, split_tosses, training_subset
from diffcontact.errors import ConfigError, DiffContactError
from diffcontact.eval.pose_metrics import ROTATION_WEIGHT, TOSS_OBJECTIVE, box_toss_metrics, toss_objective
from diffcontact.files import save_arrays, versions, write_json
from diffcontact.lock import output_lock
from diffcontact.peers import ENGINES, load_engine, require
from diffcontact.peers.cube import COM_PARAMETERS, GRAVITY, HALF_EXTENT, INERTIA, MASS, SUBSTEPS, Param, nominal
from diffcontact.run_dir import METRICS, PREDICTIONS

FAILED = 1e3  # objective of a rollout that is not finite
SIGMA0 = 0.25  # CMA-ES's initial step, in fractions of each range
DEFAULT_BUDGET = 1800  # objective evaluations
STALL_GENERATIONS = 10  # a CMA-ES run ends when its best has improved by less than STALL_IMPROVEMENT in so many
STALL_IMPROVEMENT = 0.1  # generations (objective units: % of the width); the next run restarts
TWISTS = ("fitted", "recorded", "poses")  # where the initial state of a rollout comes from (run_fit)


@dataclasses.dataclass(frozen=True)
class PeerTosses:
    """The tosses a peer is fitted and scored on: ``split_tosses(n, split, seed)`` of all the tosses, the training
    tosses (the first N of the training split, ``training_subset``, as ``diffcontact import``'s) and the table
    plane, which belongs to the setup, not to the fitted contact: from the resting frames of the whole training
    split for every N (``resting_table_height``)."""

    tosses: Tosses  # all of them
    parts: dict[str, np.ndarray]  # positions into ``tosses`` of train / val / test
    train: Tosses  # the training tosses (the first N of the training split)
    table_height: float  # m
    table_iqr: float  # m, interquartile range of the resting frames
    twist: str  # where a rollout's initial state comes from (``run_fit``)

    def part(self, name: str) -> Tosses:
        """The tosses of one part of the split (train: the whole training split; val; test)."""
        return self.tosses.subset(self.parts[name])

    def starts(self, tosses: Tosses) -> Tosses | None:
        """``tosses`` with the first states rollouts start from (twist fitted: ``with_first_states``), or None
        (the rollouts start from their recorded first frames)."""
        return with_first_states(tosses, self.table_height, [HALF_EXTENT] * 3) if self.twist == "fitted" else None


def peer_tosses(
    tosses: Tosses,
    split: tuple[float, float, float] = (0.8, 0.1, 0.1),
    seed: int = 0,
    train_tosses: int | None = None,
    twist: str = "fitted",
) -> PeerTosses:
    """The split, training tosses and table of a peer's fit (``run_fit``'s; ``train_tosses`` N: the first N of
    the training split in ``seed``'s order, all if None)."""
    parts = split_tosses(tosses.n, split, seed)
    train = tosses.subset(training_subset(parts["train"], train_tosses, seed))  # (as diffcontact import's)
    height, iqr = resting_table_height(tosses.subset(parts["train"]), [HALF_EXTENT] * 3)
    return PeerTosses(tosses, parts, train, height, iqr, twist)


def score(
    engine, tosses: Tosses, params: dict[str, float], table_height: float, starts: Tosses | None = None
) -> dict[str, float]:
    """``box_toss_metrics`` of the engine's rollouts of ``tosses`` plus ``objective``; the rollouts start from the
    first frames of ``starts`` (the same tosses with estimated first states), or of ``tosses``."""
    position, quaternion = engine.simulate(starts or tosses, params, table_height)
    return rollout_metrics(tosses, position, quaternion, table_height)


def rollout_metrics(
    tosses: Tosses, position: np.ndarray, quaternion: np.ndarray, table_height: float
) -> dict[str, float]:
    """``box_toss_metrics`` of predicted (F, 3), (F, 4) against ``tosses``, plus ``objective``; a prediction that is
    not finite gives the objective FAILED and no metrics."""
    if not (np.isfinite(position).all() and np.isfinite(quaternion).all()):
        return {"objective": FAILED}
    m = box_toss_metrics(
        position, quaternion, tosses.position, tosses.quaternion, tosses.offsets, [HALF_EXTENT] * 3, table_height
    )
    return m | {"objective": toss_objective(m)}


_WORKER: dict = {}  # a scoring process's engine, tosses, table height and first states (``_start_worker``)


def _start_worker(engine_name: str, tosses: Tosses, table_height: float, starts: Tosses | None) -> None:
    _WORKER.update(engine=load_engine(engine_name), tosses=tosses, table_height=table_height, starts=starts)


def _score_in_worker(params: dict[str, float]) -> dict[str, float]:
    w = _WORKER
    return score(w["engine"], w["tosses"], params, w["table_height"], w["starts"])


def fit_parameters(
    engine,
    tosses: Tosses,
    table_height: float,
    budget: int,
    seed: int,
    echo: Callable[[str], None] = print,
    starts: Tosses | None = None,
    space: tuple[Param, ...] | None = None,
    jobs: int = 1,
) -> dict:
    """CMA-ES with restarts (IPOP) over ``space`` (default ``engine.PARAMETERS``) on ``tosses`` (rolled out from the
    first frames of ``starts``, or of ``tosses``), within ``budget`` evaluations (whole generations; at least one).
    The first run starts from the nominal values; each later one from a seeded uniform random point with twice the
    previous population. A run ends on CMA-ES's own stop, or when its best has improved by less than
    STALL_IMPROVEMENT over STALL_GENERATIONS generations. ``jobs`` > 1 scores each generation's candidates in so
    many worker processes (the same result as one: each score depends on its parameters only). Returns the best
    parameters of all runs, their metrics and the optimiser's history."""
    space = space or engine.PARAMETERS
    with contextlib.ExitStack() as stack:
        if jobs > 1:  # (spawned, not forked: the parent holds torch's and the engines' threads)
            context, init = multiprocessing.get_context("spawn"), (engine.ENGINE, tosses, table_height, starts)
            pool = stack.enter_context(ProcessPoolExecutor(jobs, context, _start_worker, init))

            def evaluate(batch: list[dict[str, float]]) -> list[dict[str, float]]:
                return list(pool.map(_score_in_worker, batch))
        else:

            def evaluate(batch: list[dict[str, float]]) -> list[dict[str, float]]:
                return [score(engine, tosses, params, table_height, starts) for params in batch]

        return _search(evaluate, space, budget, seed, echo, jobs)


def _search(
    evaluate: Callable[[list[dict[str, float]]], list[dict[str, float]]],
    space: tuple[Param, ...],
    budget: int,
    seed: int,
    echo: Callable[[str], None],
    jobs: int,
) -> dict:
    """``fit_parameters``' search, scoring each generation's parameter sets with ``evaluate``."""
    cma = require("cma")
    rng = np.random.default_rng(seed)
    popsize0 = min(4 + int(3 * math.log(len(space))), budget)  # (CMA-ES's default, or the whole budget if smaller)
    best: dict = {"objective": math.inf}
    history: list[dict] = []
    runs: list[dict] = []
    evaluations, t0 = 0, time.perf_counter()
    while evaluations + popsize0 * 2 ** len(runs) <= budget:
        popsize = popsize0 * 2 ** len(runs)
        x0 = [p.start() for p in space] if not runs else rng.uniform(0.0, 1.0, len(space)).tolist()
        opts = {"bounds": [0.0, 1.0], "seed": seed + 1 + len(runs), "popsize": popsize}  # (cma's seed 0: the clock)
        es = cma.CMAEvolutionStrategy(x0, SIGMA0, opts | {"verbose": -9, "verb_log": 0})
        run_best: list[float] = []
        stop = "budget"
        while evaluations + popsize <= budget:
            if es.stop():
                stop = ", ".join(es.stop())
                break
            gain = run_best[-1 - STALL_GENERATIONS] - run_best[-1] if len(run_best) > STALL_GENERATIONS else math.inf
            if gain < STALL_IMPROVEMENT:
                stop = f"stalled: less than {STALL_IMPROVEMENT} better in {STALL_GENERATIONS} generations"
                break
            candidates = es.ask()
            batch = [{p.name: p.value(x) for p, x in zip(space, u)} for u in candidates]
            values = []
            for params, m in zip(batch, evaluate(batch)):
                values.append(m["objective"])
                if m["objective"] < best["objective"]:
                    best = m | {"params": params}
            es.tell(candidates, values)
            evaluations += len(candidates)
            run_best.append(min(values + run_best[-1:]))
            history.append({"run": len(runs) + 1, "generation": len(history) + 1, "evaluations": evaluations,
                            "best": min(values), "median": float(np.median(values)),
                            "best_so_far": best["objective"], "sigma": float(es.sigma),
                            "wall_time_s": time.perf_counter() - t0})  # fmt: skip
            echo(f"run {len(runs) + 1}, generation {len(history)} ({evaluations} evaluations, "
                 f"{time.perf_counter() - t0:.0f} s): best {best['objective']:.3f} (position "
                 f"{best.get('position_error_pct', math.nan):.2f} %, rotation "
                 f"{best.get('rotation_error_deg', math.nan):.2f} deg)")  # fmt: skip
        start = "nominal" if not runs else "random"
        runs.append({"popsize": popsize, "start": start, "generations": len(run_best),
                     "best": run_best[-1] if run_best else None, "stop": stop})  # fmt: skip
    return {
        "params": best["params"],
        "train_metrics": {k: v for k, v in best.items() if k != "params"},
        "optimiser": {
            "name": "IPOP-CMA-ES (cma): restarts from random points with twice the population",
            "version": metadata.version("cma"),
            "seed": seed,
            "sigma0": SIGMA0,
            "popsize": popsize0,
            "budget": budget,
            "jobs": jobs,
            "evaluations": evaluations,
            "generations": len(history),
            "stall": {"generations": STALL_GENERATIONS, "improvement": STALL_IMPROVEMENT},
            "runs": runs,
            "wall_time_s": time.perf_counter() - t0,
            "history": history,
        },
    }


def _check_request(split: tuple[float, float, float], seed: int, budget: int, twist: str, jobs: int) -> None:
    if twist not in TWISTS:
        raise ConfigError(f"twist = {twist!r} is not one of {', '.join(TWISTS)}")
    if any(f < 0 for f in split) or abs(sum(split) - 1.0) > 1e-9 or split[2] <= 0:
        raise ConfigError(f"split = {list(split)}: fractions must be >= 0, sum to 1 and give a test part")
    if seed < 0:
        raise ConfigError(f"seed = {seed} must be >= 0")
    if budget < 1:
        raise ConfigError(f"budget = {budget} must be >= 1 (objective evaluations)")
    if jobs < 1:
        raise ConfigError(f"jobs = {jobs} must be >= 1 (processes scoring the candidates)")


def run_fit(
    engine_name: str,
    source: str | Path,
    out: str | Path,
    seed: int = 0,
    split: tuple[float, float, float] = (0.8, 0.1, 0.1),
    train_tosses: int | None = None,
    budget: int = DEFAULT_BUDGET,
    twist: str = "fitted",
    echo: Callable[[str], None] = print,
    centre_of_mass: bool = True,
    jobs: int = 1,
) -> dict:
    """Fit ``engine_name`` (mujoco or bullet) on the training tosses of ``source`` (``read_tosses``; split by
    ``split_tosses(n, split, seed)``; with ``train_tosses`` N, the first N of the training split in a seeded
    order), score it and its nominal parameters on the test tosses, and write OUT/fitted.json, OUT/metrics.json
    and OUT/predictions.npz (the fitted model's test rollouts). ``twist``: the initial state of each rollout,
    the one our models start from (``fitted``: ``data.measured.first_states``, a free-flight fit), the recorded
    pose with the source's twist (``recorded``: backward differences, median-filtered) or with the one-sided
    differences of the poses (``poses``). ``centre_of_mass``: also fit the centre of mass's offset from the box
    centre (com_x, com_y, com_z, from 0; False: the centre of mass is the box centre). ``jobs``: processes that
    score the search's candidates (``fit_parameters``). Returns the metrics."""
    _check_request(split, seed, budget, twist, jobs)
    out = Path(out)
    with output_lock(out):  # (one fit at a time into a folder: a second one stops at once, naming the first)
        engine = load_engine(engine_name)
        tosses = read_tosses(source)
        if twist == "poses":
            from diffcontact.data.measured import finite_difference_twist

            velocity, omega = finite_difference_twist(tosses)
            tosses = dataclasses.replace(tosses, velocity=velocity, omega=omega)
        setting = peer_tosses(tosses, split, seed, train_tosses, twist)
        train, test, table_height = setting.train, setting.part("test"), setting.table_height
        train_starts, test_starts = setting.starts(train), setting.starts(test)
        space: tuple[Param, ...] = engine.PARAMETERS + (COM_PARAMETERS if centre_of_mass else ())
        echo(f"{engine_name}: {train.n} training tosses ({len(train.position)} frames), {test.n} test tosses, "
             f"table at z = {table_height * 1000:.3f} mm, budget {budget}, {len(space)} parameters, scored in {jobs} "
             f"process(es), load {os.getloadavg()[0]:.2f}")  # fmt: skip
        load_before = os.getloadavg()
        fit = fit_parameters(engine, train, table_height, budget, seed, echo, train_starts, space, jobs)
        start = nominal(engine.PARAMETERS)
        position, quaternion = engine.simulate(test_starts or test, fit["params"], table_height)
        lost = [int(test.toss_id[i]) for i in range(test.n) if not np.isfinite(position[test.frames_of(i)]).all()]
        if lost:
            raise DiffContactError(
                f"{engine_name}: the fitted parameters' rollouts of test tosses {lost} are not finite (the engine lost "
                f"them: unstable); nothing written"
            )
        metrics = {
            "engine": engine_name,
            "split": "test",
            "fitted": rollout_metrics(test, position, quaternion, table_height),
            "nominal": score(engine, test, start, table_height, test_starts),
            "table_height_m": table_height,
            "table_height_iqr_m": setting.table_iqr,
            "table_height_from": f"resting frames of the training split ({len(setting.parts['train'])} tosses)",
            "objective": TOSS_OBJECTIVE,
            "rotation_weight": ROTATION_WEIGHT,
            "seed": seed,
            "initial_twist": twist,
            "centre_of_mass": centre_of_mass,
            "test_toss_id": test.toss_id.tolist(),
        }
        fitted = {
            "engine": engine_name,
            "parameters": fit["params"],
            "nominal_parameters": start,
            "bounds": {p.name: {"low": p.low, "high": p.high, "log": p.log, "unit": p.unit} for p in space},
            "train_metrics": fit["train_metrics"],
            "train_metrics_nominal": score(engine, train, start, table_height, train_starts),
            "optimiser": fit["optimiser"],
            "seed": seed,
            "split": list(split),
            "train_tosses": train.n,
            "train_toss_id": train.toss_id.tolist(),
            "initial_twist": twist,
            "centre_of_mass": centre_of_mass,  # (fitted: com_x, com_y, com_z in parameters; else the box centre)
            "cube": {"half_extent_m": HALF_EXTENT, "mass_kg": MASS, "inertia_kg_m2": INERTIA, "gravity_m_s2": GRAVITY},
            "timestep_s": tosses.dt / SUBSTEPS,
            "substeps": SUBSTEPS,
            "load_average": {"start": list(load_before), "end": list(os.getloadavg())},
            "versions": versions(**{p: metadata.version(p) for p in (ENGINES[engine_name], "cma")}),
        }
        write_json(out / "fitted.json", fitted)
        write_json(out / METRICS, metrics)  # (named as an evaluation's: the toss sweep reads both alike)
        save_arrays(
            out / PREDICTIONS,
            {"position": position, "quaternion": quaternion, "offsets": test.offsets, "toss_id": test.toss_id},
        )
        return metrics
