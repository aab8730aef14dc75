"""Evaluate one trained run on a split: metrics.json, figures, rollout pictures and a GIF in ``RUN_DIR/eval/``."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Literal

import torch

from diffcontact.data.store import dataset_folder
from diffcontact.errors import DatasetError
from diffcontact.eval.loading import load_run
from diffcontact.eval.metrics import (
    energy_deviation,
    error_curve,
    mean_interval,
    relative_error,
    trajectory_error,
    true_energy,
)
from diffcontact.eval.rollouts import rollout_split
from diffcontact.eval.tosses import evaluate_tosses, measured
from diffcontact.files import save_npz, versions, write_json
from diffcontact.run_dir import METRICS, ROLLOUT, ROLLOUT_GIF, RunDir

METRICS_VERSION = 2  # 2: energy deviation relative to the energy in motion (1: to |E(z_0)|)
STEPS = 5  # frames of the Fig. 3 error (0 … 4: the training horizon)
CURVE = 50  # frames of the Fig. 4 curve and the Fig. 5 energy
FRAMES = 70  # frames rolled out (the rollout pictures, paper Figs. 7-13)
# the test trajectory shown in Fig. 5 of the paper, and 0 for the other tasks
SHOWN = {"BP5-e": 4, "CP3-e": 2, "Gyro-e": 3}


def evaluate_run(
    run: str | Path,
    split: str = "test",
    *,
    data_root: str | Path | None = None,
    task: str | None = None,
    frames: int | None = None,
    pictures: bool = True,
    out: str | Path | None = None,
    on_solver_failure: Literal["raise", "count"] = "raise",
) -> dict:
    """Evaluate the best checkpoint of ``run`` on ``split`` of its task's dataset (``data_root``: default the root
    the run was trained from) and write ``run/eval/``: metrics.json (atomically; the metrics, the run's config and
    the versions), error.png (Fig. 4), energy.png (Fig. 5), rollout.npz (the shown trajectory, truth and
    prediction), and with ``pictures`` rollout.png (every 5th frame) and rollout.gif (truth beside prediction).

    ``frames``: frames rolled out (default 70, or the split's if fewer).  ``task``: the task the caller expects
    (ConfigError for a run of another).  ``out``: the folder written (default ``run/eval``).  On measured tosses
    (``diffcontact import``) the metrics are the field's (``eval/tosses.py``), and ``on_solver_failure`` "count"
    continues past a failed contact problem (zero impulses, counted in metrics.json).  Returns the metrics.
    """
    from diffcontact.eval import animate, plots

    started = time.perf_counter()
    loaded = load_run(run, task)
    run, name = Path(run), loaded.task_name
    folder = dataset_folder(data_root or loaded.config["args"].get("data_root", "data"), name)
    if measured(folder):  # (recorded tosses: whole tosses from their first state, scored in the field's metrics)
        record = {"task": name, "model": loaded.model_name, "run_dir": str(run), "checkpoint": str(loaded.checkpoint)}
        record |= {"learned": _learned(run), "config": loaded.config}
        out = out or RunDir(run).eval_dir()
        return evaluate_tosses(loaded.net, folder, out, split, pictures, on_solver_failure, **record)
    if frames is None:
        from diffcontact.data.store import load_meta

        frames = min(FRAMES, int(load_meta(folder)["request"]["frames"]))
    ro = rollout_split(loaded.net, folder, split, frames, loaded.task.config)
    N, T = ro.x.shape[:2]
    rel = relative_error(ro.x_hat, ro.v_hat, ro.x, ro.v, diverged_ok=True)  # (+inf where the model diverged)
    finite = torch.isfinite(rel)
    diverged = {int(n): int((~finite[n]).nonzero()[0]) for n in (~finite.all(1)).nonzero().flatten()}
    steps, curve_len = min(STEPS, T), min(CURVE, T)
    per_traj = trajectory_error(rel, steps)
    mean, half = mean_interval(per_traj)
    energy, kinetic = true_energy(loaded.task, ro.x, ro.v)
    energy_hat, _ = true_energy(loaded.task, ro.x_hat, ro.v_hat)
    dev = energy_deviation(energy_hat[:, :curve_len], energy[:, :curve_len], kinetic[:, :curve_len])
    dev = dev.nan_to_num(nan=float("inf")).amax(1)  # (N,) (+inf for a trajectory that diverged)
    shown = min(SHOWN.get(name, 0), N - 1)
    metrics = {
        "metrics_version": METRICS_VERSION,
        "task": name,
        "model": loaded.model_name,
        "run_dir": str(run),
        "checkpoint": str(loaded.checkpoint),
        "split": split,
        "n_trajectories": N,
        "frames": T,
        "dt": ro.dt,
        "ground_truth": "test trajectories: exact contact model (CM), float64, from the same initial states",
        "diverged": {"trajectories": len(diverged), "first_nonfinite_frame": diverged},
        "trajectory_error": {"steps": steps, "mean": mean, "ci95": half, "per_trajectory": per_traj.tolist()},
        "error_curve": error_curve(rel, curve_len).tolist(),
        "energy": {
            "frames": curve_len,
            "relative_to": "the largest true kinetic energy of each trajectory over the frames",
            "max_rel_deviation_mean": float(dev.mean()),
            "max_rel_deviation_max": float(dev.max()),
            "shown_trajectory": shown,
            "shown_true": energy[shown, :curve_len].tolist(),
            "shown_predicted": energy_hat[shown, :curve_len].tolist(),
        },
        "learned": _learned(run),
        "config": loaded.config,
        "versions": versions(),
    }
    out = Path(out or RunDir(run).eval_dir())
    out.mkdir(parents=True, exist_ok=True)
    dts = {name: ro.dt}
    plots.error_curves({name: {loaded.model_name: metrics["error_curve"]}}, dts, out / "error.png")
    truth, pred = metrics["energy"]["shown_true"], metrics["energy"]["shown_predicted"]
    plots.energy_panels({name: {"truth": truth, loaded.model_name: pred}}, dts, out / "energy.png")
    save_npz(out / ROLLOUT, x=ro.x[shown].numpy(), x_hat=ro.x_hat[shown].numpy(), contact=ro.contact[shown])
    if pictures:
        system, xs, xh, hit = loaded.task.system, ro.x[shown].numpy(), ro.x_hat[shown].numpy(), ro.contact[shown]
        animate.rollout_strip(system, {"truth": xs, loaded.model_name: xh}, hit.numpy(), out / "rollout.png", ro.dt)
        animate.compare_gif(system, xs, xh, hit.numpy(), out / ROLLOUT_GIF, ro.dt)
    metrics["seconds"] = time.perf_counter() - started  # (the evaluation's wall time, pictures included)
    write_json(out / METRICS, metrics)  # (last: its presence marks a finished evaluation)
    return metrics


def evaluated(run: str | Path, task: str, model: str) -> dict | None:
    """The metrics of the run's finished evaluation (eval/metrics.json) if they are of (task, model) and of the
    current metrics, else None."""
    metrics = RunDir(run).metrics()
    if metrics is None:
        return None
    same = (metrics.get("task"), metrics.get("model"), metrics.get("metrics_version")) == (task, model, METRICS_VERSION)
    return metrics if same else None


def _learned(run: Path) -> dict | None:
    """μ, e, mass ratios, moments and the centre of mass (a box), learned against true (nominal, on measured data),
    from the run's learned.json (None if it has none)."""
    if not RunDir(run).learned.is_file():
        return None
    learned = RunDir(run).read_learned()
    keys = ("mu", "e", "mass_ratio", "moments", "centre_of_mass", "inertia")
    return {k: learned[k] for k in keys if k in learned}


def evaluate_nominal(
    task: str, data_root: str | Path, out: str | Path, split: str = "test", pictures: bool = True
) -> dict:
    """Evaluate a task's simulator with the task file's own (nominal) values on the measured tosses of its dataset
    (``data_root``: the dataset folder or its root) into ``out``; returns the metrics."""
    from diffcontact.models.model import known_model
    from diffcontact.systems.registry import build_task

    built = build_task(task)
    folder = dataset_folder(data_root, built.config.name)
    if not measured(folder):
        raise DatasetError(f"{folder}: --nominal evaluates measured tosses (diffcontact import), not simulated data")
    model = "nominal (the task file's values, exact model CM)"
    return evaluate_tosses(known_model(built), folder, out, split, pictures, task=built.config.name, model=model)
