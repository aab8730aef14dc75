"""The control commands: optimise, report the loss per simulation with a progress bar, write the outputs.

``diffcontact control billiards`` and ``diffcontact control throw`` (the paper's control tasks) call
:func:`run_billiards` and :func:`run_throw`. The one random choice, the billiards search's cue lines, takes a
seed (default 0, recorded in the JSON); the optimisers are deterministic.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import torch

from diffcontact.control.billiards import Billiards
from diffcontact.control.optimise import OPTIMISERS, History, adam, levenberg_marquardt
from diffcontact.control.outputs import loss_curves, motion_gif, write_result
from diffcontact.control.throw import MODES, Physics, Throw
from diffcontact.errors import ConfigError

PUBLISHED_BILLIARDS = {1: 0.04548, 2: 0.02902}  # the published run: the first two iterations (200 in all, SGD lr 0.01)
PUBLISHED_FINAL_STATE = (0.12431, 0.44550, 0.48702, 0.03730)  # the published notebook billiards.ipynb, iteration 199
BILLIARDS_SCALE = (0.1, 0.1, 0.1, 0.1)  # θ = (p, v) in units of 0.1 m and 0.1 m/s
BILLIARDS_RADIUS = 0.1  # LM's first step: at most 0.01 m / 0.01 m/s (the published SGD's first step is ~0.01)
SEARCH_SPEED = 1.5  # m/s: the global stage's shots; time scaling gives every slower speed on their lines


def optimise(
    residual,
    theta0: torch.Tensor,
    optimiser: str,
    max_simulations: int,
    tol: float,
    scale: torch.Tensor,
    radius: float,
    trials: int,
    lr: float,
    label: str,
    echo: Callable[[str], None] | None,
    progress: bool,
) -> History:
    """Run ``optimiser`` (OPTIMISERS) on ‖residual‖² from θ0 until ‖r‖ <= ``tol`` or ``max_simulations``, with a
    tqdm bar and one line per simulation through ``echo``; θ is scaled by ``scale`` (n,), LM's first trust radius
    is ``radius`` (``trials`` step lengths per simulation) and Adam's learning rate ``lr`` (both in scaled units)."""
    from tqdm import tqdm

    if optimiser not in OPTIMISERS:
        raise ConfigError(f"optimiser = {optimiser!r} is not one of {list(OPTIMISERS)}")
    bar = tqdm(total=max_simulations, desc=label, disable=not progress, leave=False)

    def report(hist: History) -> None:
        bar.update(1)
        bar.set_postfix(loss=f"{hist.loss:.3e}")
        if echo is not None:
            kept = "" if hist.accepted[-1] else "  (rejected)"
            line = f"{label} {hist.simulations:3d}: loss {hist.losses[-1]:.6g}{kept}"
            bar.write(line) if progress else echo(line)

    try:
        if optimiser == "lm":
            return levenberg_marquardt(
                residual,
                theta0,
                max_simulations,
                tol=tol**2,
                scale=scale,
                radius=radius,
                trials=trials,
                progress=report,
            )
        return adam(residual, theta0, max_simulations, lr=lr, tol=tol**2, scale=scale, progress=report)
    finally:
        bar.close()


def _best(hist: History) -> torch.Tensor:
    """The best θ of a finished optimisation (which records its start: never None)."""
    if hist.theta is None:
        raise ValueError("the optimisation recorded no θ")
    return hist.theta


def _history(hist: History) -> dict:
    return {
        "losses": hist.losses,
        "thetas": hist.thetas,
        "accepted": hist.accepted,
        "simulations": hist.simulations,
        "steps_accepted": sum(hist.accepted) - 1,
        "trajectories": hist.trajectories,
        "best_theta": _best(hist).tolist(),
        "best_loss": hist.loss,
        "stop": hist.stop,
    }


def run_billiards(
    out: str | Path,
    balls: int = 11,
    frames: int | None = None,
    optimiser: str = "lm",
    max_simulations: int = 200,
    tol: float = 1e-6,
    trials: int = 8,
    lr: float = 0.01,
    search_shots: int = 256,
    search_rounds: int = 3,
    seed: int = 0,
    starts: int = 4,
    gif: bool = True,
    published: bool = True,
    echo: Callable[[str], None] | None = print,
    progress: bool = True,
) -> dict:
    """Optimise the cue ball's (p, v) so that the last ball ends within ``tol`` m of the goal, at most
    ``max_simulations`` simulations; write OUT/billiards_loss.png, billiards_shot.gif and billiards.json.

    With ``search_shots`` > 0 the first ``search_rounds`` simulations are the global stage
    (:meth:`Billiards.search`: that many cue lines per round, seeded by ``seed``, in one batch each), and LM starts
    from its ``starts`` nearest candidates at once (one batch per simulation; Adam from the nearest); with 0 it
    starts from the task file's θ0 (the published setting). ``published``: also simulate the published final cue
    state with the published end-of-step scheme, for the loss curve's reference point at iteration 200
    (on the published table only, as are the published points). Returns the JSON's content."""
    if search_shots < 0:
        raise ConfigError(f"search_shots = {search_shots} is not >= 0")
    if starts < 1:
        raise ConfigError(f"starts = {starts} is not >= 1")
    if search_shots and max_simulations <= search_rounds:
        raise ConfigError(
            f"max_simulations = {max_simulations} is not > search_rounds = {search_rounds} (the search's simulations "
            "and the optimiser's start)"
        )
    out = Path(out)
    t0 = time.perf_counter()
    shot = Billiards.build(balls=balls, frames=frames)
    scale = torch.tensor(BILLIARDS_SCALE, dtype=torch.float64)
    curve: list[float] = []
    search = None
    thetas = shot.theta0[None]
    if search_shots:
        found = shot.search(search_shots, seed, SEARCH_SPEED, rounds=search_rounds)
        if not len(found.thetas):
            raise ConfigError(f"no feasible shot among the search's {search_shots} (seed {seed})")
        curve += [d**2 for d in found.nearest]
        thetas = found.thetas[:starts]
        search = {
            "shots_per_round": search_shots,
            "rounds": search_rounds,
            "shots": search_shots * search_rounds,
            "seed": seed,
            "speed_m_s": SEARCH_SPEED,
            "nearest_per_round_m": found.nearest,
            "nearest_distances_m": found.distances[:8].tolist(),
            "starts": thetas.tolist(),
            "wall_time_s": time.perf_counter() - t0,
        }
        if echo is not None:
            for i, d in enumerate(found.nearest):
                echo(f"billiards search {i + 1}: {search_shots} shots in one batch, nearest {d:.3g} m from the goal")
    if optimiser == "adam":
        thetas = thetas[0]  # (Adam: one start)
    hist = optimise(shot.residual, thetas, optimiser, max_simulations - len(curve), tol, scale, BILLIARDS_RADIUS,
                    trials, lr, "billiards", echo, progress)  # fmt: skip
    curve += hist.losses
    wall = time.perf_counter() - t0
    with torch.no_grad():
        x, hit, _ = shot.rollout(_best(hist)[None])
    result = {
        "problem": "billiards",
        "config": {
            "task": shot.task.config.name,
            "balls": balls,
            "frames": shot.task.frames,
            "dt": shot.task.dt,
            "time_of_impact": True,
            "optimiser": optimiser,
            "max_simulations": max_simulations,
            "tol_m": tol,
            "trials": trials if optimiser == "lm" else 1,
            "lr": lr if optimiser == "adam" else None,
            "search_shots": search_shots,
            "search_rounds": search_rounds if search_shots else 0,
            "seed": seed if search_shots else None,
            "starts": starts if search_shots else 1,
            "theta0": shot.theta0.tolist(),
            "goal": shot.goal.tolist(),
            "theta": "cue ball (p_x, p_y, v_x, v_y) in m, m/s",
            "loss": "|x_last(T) - goal|^2 in m^2",
        },
        "search": search,
        "optimisation": _history(hist),
        "losses": curve,
        "simulations": len(curve),
        "steps_accepted": sum(hist.accepted) - 1,
        "trajectories": (search["shots"] if search else 0) + hist.trajectories,
        "best_theta": _best(hist).tolist(),
        "best_loss": hist.loss,
        "stop": hist.stop,
        "final_position": x[0, -1, -1].tolist(),
        "final_distance_m": float((x[0, -1, -1] - shot.goal).norm()),
        "wall_time_s": wall,
        "published": {"first_iterations": PUBLISHED_BILLIARDS, "iterations": 200},
    }
    published_table = balls == 11 and shot.task.frames == 1024
    markers = {"published, iterations 1-2": PUBLISHED_BILLIARDS} if published_table else {}
    if published and published_table:
        ref = Billiards.build(time_of_impact=False)
        with torch.no_grad():
            r = ref.residual(torch.tensor([PUBLISHED_FINAL_STATE], dtype=torch.float64))[0]
        result["published"]["final_state"] = list(PUBLISHED_FINAL_STATE)
        result["published"]["final_state_loss_ours_published_scheme"] = float(r @ r)
        markers["published state at iteration 200, in our simulator"] = {200: float(r @ r)}
    what = f"search ({search_rounds} x {search_shots} shots) + " if search_shots else ""
    loss_curves(
        {f"ours: {what}{optimiser.upper()}, time of impact": curve}, out / "billiards_loss.png",
        f"billiards ({balls} balls, {shot.task.frames} frames): |x_last(T) - goal|^2", markers,
    )  # fmt: skip
    if gif:
        motion_gif(
            shot.task.system, {"final shot": x[0].numpy()}, {"final shot": hit[0].numpy()}, shot.goal.numpy(),
            out / "billiards_shot.gif", shot.task.dt, every=8,
        )  # fmt: skip
    write_result(out / "billiards.json", result)
    return result


def run_throw(
    out: str | Path,
    run: str | Path | None = None,
    modes: tuple[str, ...] = MODES,
    optimiser: str = "lm",
    max_simulations: int = 30,
    tol: float = 1e-5,
    trials: int = 1,
    lr: float = 0.1,
    gif: bool = True,
    echo: Callable[[str], None] | None = print,
    progress: bool = True,
) -> dict:
    """The throws of ``modes`` with the true properties and, given a ``diffcontact train`` run, with its learned
    ones; each learned-property throw is replayed with the true properties and its landing (the centre at the
    second ground impact) compared with the true-property throw's. Writes OUT/throw_MODE_loss.png,
    throw_MODE.gif and throw.json; returns the JSON's content. ``tol``: stop at ‖r‖ <= tol (m or m/s)."""
    out = Path(out)
    learned = Physics.learned(run) if run is not None else None
    true = Physics.true(learned.task if learned is not None else "BD1")
    result: dict = {
        "problem": "throw",
        "config": {
            "task": true.task.config.name,
            "dt": true.task.dt,
            "time_of_impact": True,
            "from": str(run) if run else None,
            "optimiser": optimiser,
            "max_simulations": max_simulations,
            "tol": tol,
            "trials": trials if optimiser == "lm" else 1,
            "lr": lr if optimiser == "adam" else None,
            "modes": list(modes),
        },
    }
    if learned is not None:
        p = learned.params
        result["learned_properties"] = {
            "mu": p.mu.tolist()[:1],
            "e": p.e.tolist()[:1],
            "mass": p.inertia.masses.tolist(),
        }
    for mode in modes:
        entry: dict = {}
        curves, rows, flags = {}, {}, {}
        true_problem = Throw(true, mode)
        scale = torch.tensor([1.0, 1.0, 10.0] if mode == "hit" else [10.0], dtype=torch.float64)  # m/s, rad/s
        landing_true = None
        for physics in (true, learned):
            if physics is None:
                continue
            problem = Throw(physics, mode)
            t0 = time.perf_counter()
            hist = optimise(problem.residual, problem.theta0, optimiser, max_simulations, tol, scale, 1.0, trials, lr,
                            f"{mode} ({physics.label})", echo, progress)  # fmt: skip
            key = "true" if physics is true else "learned"
            landings = true_problem.landings(_best(hist))  # (replayed with the true properties)
            entry[key] = {**_history(hist), "wall_time_s": time.perf_counter() - t0, "landings_true_physics": landings}
            if physics is true:
                landing_true = landings[-1]
            else:
                gap = torch.tensor(landings[-1]) - torch.tensor(landing_true)
                entry[key]["landing_distance_to_true_throw_m"] = float(gap.norm())
            curves[physics.label] = hist.losses
            frames = int(true_problem.bounce_frames(_best(hist)[None], 2)[2][0, -1]) + 15
            x, hit = true_problem.trajectory(_best(hist), frames)
            label = "true properties" if physics is true else "learned properties (replayed true)"
            rows[label], flags[label] = x.numpy(), hit.numpy()
        what = "centre at 2nd ground impact - target" if mode == "hit" else "v_x after the 1st ground impact"
        loss_curves(curves, out / f"throw_{mode}_loss.png", f"throw '{mode}' (BD1): loss |{what}|^2")
        if gif:
            target = torch.tensor(true_problem.target if mode == "hit" else landing_true).numpy()
            motion_gif(true.task.system, rows, flags, target, out / f"throw_{mode}.gif", true.task.dt, every=2)
        result[mode] = entry
    write_result(out / "throw.json", result)
    return result
