"""Command line: thin subcommands that parse arguments and call the library."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager

import typer

from diffcontact.eval.published import EFFICIENCY_SIZES

app = typer.Typer(
    help="diffcontact: differentiable contact models for learning rigid-body dynamics.",
    no_args_is_help=True,
    add_completion=False,
)
TASK_HELP = (
    "A packaged task's name (e.g. BP5-e; diffcontact/tasks/NAME.toml) or the path of a task file (./my_task.toml)."
)


@contextmanager
def _user_errors() -> Iterator[None]:
    """A user's mistake (a DiffContactError: a bad setting, a dataset or run that does not fit, a locked output),
    a diverging simulation or an output that cannot be written ends the command with one line on stderr and exit
    code 2, no traceback (DIFFCONTACT_TRACEBACK=1 shows it)."""
    from diffcontact.errors import DiffContactError

    try:
        yield
    except (DiffContactError, FloatingPointError, OSError) as err:
        if os.environ.get("DIFFCONTACT_TRACEBACK"):
            raise
        typer.echo(f"{type(err).__name__}: {err}", err=True)
        raise typer.Exit(2) from err


bench_app = typer.Typer(help="Benchmarks (medians and ratios measured in one run).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

THREADS = typer.Option(
    None,
    "--threads",
    min=1,
    help="Threads of torch, numba and the contact solver (default: the CPUs available to this process, from its "
    "affinity and cgroup quota).",
)


def _threads(threads: int | None) -> int:
    """Apply the --threads option (diffcontact.threads.set_threads); returns the number used."""
    from diffcontact.threads import set_threads

    return set_threads(threads)


@bench_app.command("solver")
def bench_solver(
    batch: list[int] = typer.Option([1, 128, 800], "--batch", "-b", help="Batch sizes B."),
    contacts: list[int] = typer.Option([1, 2, 3, 5, 19], "--contacts", "-k", help="Contact counts K."),
    dims: list[int] = typer.Option(
        [1, 2, 3], "--dim", "-d", help="Contact-space dimensions d (1: frictionless limits, as the rope's)."
    ),
    repeats: int = typer.Option(7, help="Timed repetitions of our solver (median reported)."),
    reference: bool = typer.Option(True, help="Also time the cvxpylayers reference (needs the extra)."),
    ref_max_batch: int = typer.Option(
        64, help="Time the reference on at most this many problems per setting (its cost is per problem)."
    ),
    seed: int = typer.Option(0, help="Seed of the random instances."),
    threads: int = THREADS,
    out: str = typer.Option("", help="Also write the table as Markdown to this file."),
) -> None:
    """Forward+backward time per problem of the contact solver against the cvxpylayers reference."""
    _threads(threads)
    from diffcontact.bench.solver import run_solver_benchmark

    with _user_errors():
        run_solver_benchmark(
            batches=batch,
            contacts=contacts,
            dims=dims,
            repeats=repeats,
            reference=reference,
            ref_max_batch=ref_max_batch,
            seed=seed,
            out=out or None,
        )


@app.command("simulate")
def simulate(
    task: str = typer.Argument(..., help=TASK_HELP),
    n: int = typer.Option(16, "--n", help="Number of trajectories N."),
    steps: int = typer.Option(0, "--steps", help="Frames T per trajectory (0 = the task's frames)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the initial conditions."),
    out: str = typer.Option(..., "--out", help="Output .npz: x, v (N,T,P,d), t, energy, contact, config, meta."),
    gif: str = typer.Option("", "--gif", help="Also render trajectory 0 to this GIF."),
    threads: int = THREADS,
    dynamics: str = typer.Option("lagrangian", help="lagrangian (x, v) or hamiltonian (x, p)."),
) -> None:
    """Simulate a task with its true parameters (exact contact model CM, float64)."""
    _threads(threads)
    from diffcontact.simulate import simulate_task

    with _user_errors():
        meta = simulate_task(task, n, None if steps == 0 else steps, seed, out, gif or None, dynamics)
    typer.echo(f"wrote {out}: {meta['n']} trajectories x {meta['frames']} frames of {meta['task']}")


@app.command("generate")
def generate(
    task: str = typer.Argument("", help=TASK_HELP + " Omit with --all."),
    all_tasks: bool = typer.Option(False, "--all", help="Generate the 8 benchmark tasks."),
    out: str = typer.Option("data", "--out", help="Root folder; each task goes to OUT/TASK/."),
    noise: float = typer.Option(0.0, "--noise", help="Std of Gaussian noise on the chunk frames (0 = none)."),
    n_train: int = typer.Option(800, "--n-train", help="Training trajectories."),
    n_val: int = typer.Option(100, "--n-val", help="Validation trajectories."),
    n_test: int = typer.Option(100, "--n-test", help="Test trajectories."),
    seeds: tuple[int, int, int] = typer.Option((0, 1, 2), "--seeds", help="Seeds of train, val and test."),
    force: bool = typer.Option(
        False, "--force", help="Regenerate even if an identical valid dataset exists, or replace one of other sizes."
    ),
    workers: int = typer.Option(1, "--workers", help="Processes simulating the trajectories (the same bytes for any)."),
    threads: int = THREADS,
    progress: bool = typer.Option(True, help="Show a progress bar."),
) -> None:
    """Generate train/val/test trajectories and 5-frame chunks of a task (CM, float64), with checksums."""
    _threads(threads)
    import time

    from diffcontact.data.generate import generate_dataset
    from diffcontact.systems.registry import BENCHMARK_TASKS

    if all_tasks == bool(task):
        raise typer.BadParameter("give either a TASK or --all")
    t0 = time.perf_counter()
    names = list(BENCHMARK_TASKS) if all_tasks else [task]
    with _user_errors():
        for name in names:
            generate_dataset(
                name, out, n_train=n_train, n_val=n_val, n_test=n_test, seeds=seeds, noise=noise,
                force=force, progress=progress, echo=typer.echo, workers=workers,
            )  # fmt: skip
    typer.echo(f"done: {len(names)} task(s) in {time.perf_counter() - t0:.1f} s -> {out}")


import_app = typer.Typer(help="Import measured trajectories as a dataset.", no_args_is_help=True)
app.add_typer(import_app, name="import")


@import_app.command("contactnets")
def import_contactnets(
    source: str = typer.Argument(
        ..., help="A folder of ContactNets K.pt files, a tosses .npz in that layout, or 'sample' (20 shipped tosses)."
    ),
    out: str = typer.Option(..., "--out", help="The dataset folder to write (e.g. data/CubeToss)."),
    split: tuple[float, float, float] = typer.Option((0.8, 0.1, 0.1), "--split", help="Train, val, test fractions."),
    seed: int = typer.Option(0, "--seed", help="Seed of the split by toss."),
    all_test: bool = typer.Option(False, "--all-test", help="Every toss in the test split (evaluation only)."),
    task: str = typer.Option("CubeToss", "--task", help="The box task the tosses are of."),
    train_tosses: int = typer.Option(
        None, "--train-tosses", help="Keep only N training tosses (seeded, nested; val and test unchanged)."
    ),
    window: int = typer.Option(80, "--window", help="Frames of a training window (every toss needs as many)."),
    stride: int = typer.Option(80, "--stride", help="Frames between the starts of a toss's windows."),
) -> None:
    """Import the ContactNets cube tosses (real poses of a real cube): SI units, the table at z = 0, splits by toss."""
    from diffcontact.data.measured import import_tosses

    with _user_errors():
        import_tosses(
            source,
            out,
            task=task,
            split=split,
            seed=seed,
            all_test=all_test,
            train_tosses=train_tosses,
            window=window,
            stride=stride,
            echo=typer.echo,
        )


@app.command("train")
def train(
    task: str = typer.Argument(..., help=TASK_HELP + " Its dataset must exist: diffcontact generate TASK."),
    model: str = typer.Option(
        None,
        "--model",
        help="CM-CD-CLNN (default), CM-CD-CHNN, CMr-CD-CLNN, CMr-CD-CHNN; baselines MLP-CD-CLNN, IN-CP-CLNN, IN-CP-SP.",
    ),
    preset: str = typer.Option(
        None,
        "--preset",
        help="Training settings: default (200 epochs, batch 50, lr 1e-2 cosine-annealed, projected μ and e) or "
        "published (1000 epochs, batch 200, lr 1e-3 constant, ReLU μ, hardsigmoid e).",
    ),
    epochs: int = typer.Option(None, "--epochs", help="Epochs (default: the preset's)."),
    seed: int = typer.Option(None, "--seed", help="Seed of the initial parameters and the batch order (default 0)."),
    out: str = typer.Option("", "--out", help="Run directory (default runs/TASK/MODEL/seedS)."),
    data: str = typer.Option(
        None, "--data", help="Dataset root (as given to diffcontact generate --out; default data)."
    ),
    batch_size: int = typer.Option(None, "--batch-size", help="Chunks per batch (default: the preset's)."),
    lr: float = typer.Option(None, "--lr", help="AdamW learning rate (default: the preset's)."),
    schedule: str = typer.Option(
        None, "--schedule", help="Learning rate over the epochs: constant or cosine (to lr/100; default: the preset's)."
    ),
    coef_lr: float = typer.Option(
        None, "--coef-lr", help="Learning rate of μ and e relative to the others (default: the preset's)."
    ),
    mu_coef_lr: float = typer.Option(
        None, "--mu-coef-lr", help="Learning rate of μ relative to the others (default: the preset's or --coef-lr)."
    ),
    mu_l1: float = typer.Option(
        None,
        "--mu-l1",
        help="Weight of an L1 pull of the learned μ toward 0 in the training loss (+ mu_l1·Σμ; default: the "
        "preset's). It moves μ off the plateau where every contact of a slot sticks (docs/investigations.md).",
    ),
    reg: float = typer.Option(
        None, "--reg", help="CMr models: the regularisation A + reg·I of the effective mass (default 0.01)."
    ),
    smooth: bool = typer.Option(False, "--smooth", help="softplus μ and sigmoid e instead of the preset's."),
    train_loss: str = typer.Option(
        None, "--train-loss", help="l1 (default, the paper's) or mse (measured for the baselines: docs/baselines.md)."
    ),
    resume: bool = typer.Option(
        False,
        "--resume",
        help="Continue the run in --out from its last checkpoint, with its settings (config.json); options given must "
        "equal them (--epochs may grow with a constant schedule).",
    ),
    devices: int = typer.Option(
        None, "--devices", help="Processes per machine (DDP when more than one; default 1, or the run's with --resume)."
    ),
    num_nodes: int = typer.Option(None, "--num-nodes", help="Machines (default 1): docs/scaling.md."),
    accelerator: str = typer.Option(
        "cpu",
        "--accelerator",
        help="cpu, the only one (docs/scaling.md, GPUs).",
    ),
    threads: int = typer.Option(
        1,
        "--threads",
        min=1,
        help="Threads of torch, numba and the contact solver in each process. Default 1: a step's tensors are small, "
        "and on 2 idle cores 2 threads made it 1.5x slower (docs/speed.md); use more cores with --devices.",
    ),
    progress: bool = typer.Option(True, help="Show a progress bar."),
) -> None:
    """Train a model on a task's chunks; writes checkpoints, logs and learned.json into the run directory."""
    _threads(threads)
    from diffcontact.train.run import train_run

    with _user_errors():
        summary = train_run(
            task, model, preset=preset, epochs=epochs, seed=seed, out=out or None, data_root=data,
            batch_size=batch_size, lr=lr, schedule=schedule, coef_lr=coef_lr,
            mu_coef_lr=mu_coef_lr, mu_l1=mu_l1, reg=reg, train_loss=train_loss,
            mu_transform="softplus" if smooth else None, e_transform="sigmoid" if smooth else None, resume=resume,
            progress=progress, devices=devices, num_nodes=num_nodes, accelerator=accelerator,
        )  # fmt: skip
    if summary["rank"] != 0:  # (another process of a DDP run: the first one reports)
        return
    typer.echo(f"run: {summary['run_dir']}  ({summary['wall_time_s']:.0f} s, best epoch: {summary['best_checkpoint']})")
    for key in ("mu", "e", "mass_ratio", "moments"):
        if key not in summary:
            continue
        item = summary[key]
        versus = "nominal" if "nominal" in item else "true"  # (measured data: the task's values are nominal)
        learned, true = item["learned"], item[versus]
        if len(set(true)) == 1 and len(set(learned)) == 1:  # homogeneous: one value for every slot
            learned, true = learned[:1], true[:1]
        shown = ", ".join(f"{a:.4f}/{b:.4f}" for a, b in zip(learned[:8], true[:8]))
        more = f" … ({len(learned)} values)" if len(learned) > 8 else ""
        err = item["max_abs_error" if versus == "true" else "max_abs_from_nominal"]
        hidden = item.get("identifiable", []).count(False)
        note = f" ({hidden} slots without the contacts that identify it)" if hidden and err is not None else ""
        shown_err = "not identifiable from the training data" if err is None else f"{err:.4f}{note}"
        what = "max |error|" if versus == "true" else "max |learned - nominal|"
        typer.echo(f"{key:10s} learned/{versus}: {shown}{more}   {what} = {shown_err}")
    if not summary["inertia"].get("given"):  # (IN-CP-SP learns no inertia)
        spread = summary["inertia"]["spread"]
        typer.echo(f"inertia    on the motions the constraints allow, up to the potential's scale: within {spread:.2%}")


@app.command("summarize")
def summarize(run: str = typer.Argument(..., help="Run directory of a finished `diffcontact train`.")) -> None:
    """Recompute a run's learned.json (learned against true, what the data identify) from its best checkpoint."""
    from diffcontact.train.run import summarize_run

    with _user_errors():
        summary = summarize_run(run)
    errors = ("max_abs_error", "max_abs_from_nominal")  # (against the truth; on measured data, the nominal values)
    shown = {k: {e: v for e, v in summary[k].items() if e in ("learned", *errors)} for k in ("mu", "e", "mass_ratio")}
    typer.echo(json.dumps(shown))


@app.command("spread")
def spread(
    runs: list[str] = typer.Argument(..., help="Run directories of one task and model (e.g. seeds 0, 1, 2)."),
    eval_name: str = typer.Option("eval", "--eval", help="Each run's evaluation folder whose metrics are included."),
    out: str = typer.Option("", "--out", help="Also write the values as JSON to this file."),
) -> None:
    """The learned values (μ, e, inertia, centre of mass, g, table height) and the evaluation of several runs side by
    side: each run's value, their mean, standard deviation and range."""
    from diffcontact.eval.spread import spread as runs_spread
    from diffcontact.eval.spread import spread_table
    from diffcontact.files import check_output, versions, write_json

    with _user_errors():
        target = check_output(out, "--out") if out else None
        result = runs_spread(runs, eval_name)
        if target is not None:
            write_json(target, result | {"versions": versions()})
    typer.echo(spread_table(result))


@app.command("evaluate")
def evaluate(
    run: str = typer.Argument(..., help="Run directory of a finished `diffcontact train`."),
    split: str = typer.Option("test", "--split", help="Dataset split: test, val or train."),
    data: str = typer.Option("", "--data", help="Dataset root (default: the one the run was trained from)."),
    task: str = typer.Option("", "--task", help="Refuse a run of any other task than this one (name or task file)."),
    frames: int = typer.Option(None, "--frames", help="Frames rolled out (default 70, or the split's if fewer)."),
    threads: int = THREADS,
    pictures: bool = typer.Option(True, help="Also draw the rollout picture and GIF."),
    out: str = typer.Option("", "--out", help="The folder written (default RUN/eval)."),
    nominal: bool = typer.Option(
        False, "--nominal", help="RUN is a task: evaluate its simulator with the task file's own values (no training)."
    ),
    on_solver_failure: str = typer.Option(
        "raise",
        "--on-solver-failure",
        help="Measured tosses: raise, or count (zero impulses, counted in metrics.json).",
    ),
) -> None:
    """Metrics of a run's best model on a split: on simulated data the 5-step error, error curve and true energy
    against the exact model; on measured tosses (diffcontact import) the position, rotation and penetration errors."""
    _threads(threads)
    if on_solver_failure not in ("raise", "count"):
        raise typer.BadParameter(f"{on_solver_failure!r} is not raise or count", param_hint="--on-solver-failure")
    failure = "count" if on_solver_failure == "count" else "raise"
    from diffcontact.eval.evaluate import evaluate_nominal, evaluate_run
    from diffcontact.run_dir import RunDir

    dest = out or (f"runs/{run}-nominal/eval" if nominal else str(RunDir(run).eval_dir()))
    with _user_errors():  # (a bad run or data, a failed solve, a diverging model)
        if nominal:
            m = evaluate_nominal(run, data or "data", dest, split)
        else:
            m = evaluate_run(
                run, split, data_root=data or None, task=task or None, frames=frames, pictures=pictures,
                out=out or None, on_solver_failure=failure,
            )  # fmt: skip
    if "position_error_pct" in m:
        typer.echo(f"{m['task']} {m['model']}: position error {m['position_error_pct']:.2f} % of the width, "
                   f"rotation {m['rotation_error_deg']:.2f} deg, penetration {m['penetration_pct']:.3f} % "
                   f"({m['tosses']} tosses, {m['frames']} frames); {m['diverged']['tosses']} diverged, "
                   f"{sum(m['solver']['failures'].values())} failed contact problems counted -> {dest}")  # fmt: skip
        return
    err5, energy = m["trajectory_error"], m["energy"]
    half = "n/a" if err5["ci95"] is None else f"{err5['ci95']:.3g}"
    typer.echo(f"{m['task']} {m['model']}: {err5['steps']}-step error {err5['mean']:.4g} ± {half} (95 %, "
               f"{m['n_trajectories']} trajectories); energy within {energy['max_rel_deviation_max']:.3g} of the "
               f"energy in motion over {energy['frames']} frames; {m['diverged']['trajectories']} trajectories "
               f"diverged -> {dest}")  # fmt: skip


def _split(values: list[str]) -> list[str]:
    """Values of a repeatable option, each of which may also be a comma-separated list."""
    return [v.strip() for value in values for v in value.split(",") if v.strip()]


ALL_AT_ONCE = 100_000  # (--jobs of a cluster backend: every cell submitted, the cluster queues them)
SEEDS = typer.Option(["0"], "--seeds", "-s", help="Seeds of each (task, model), e.g. -s 0,1,2.")
JOBS = typer.Option(
    None,
    "--jobs",
    "-j",
    min=1,
    help="Runs at a time, one process each (default: one per available CPU, as memory allows: 1.5 GB each; "
    "with --backend ray or slurm every run at once, the cluster queues them).",
)
BACKEND = typer.Option(
    "local", "--backend", help="Where the runs go: local (this machine), ray (a Ray cluster) or slurm (submitit)."
)
ADDRESS = typer.Option(
    None, "--address", help="With --backend ray: the cluster to join ('auto': this node's; default: a new one)."
)
EPOCHS = typer.Option(None, "--epochs", min=1, help="Epochs of every run (default: each task's preset).")
PARTITION = typer.Option(None, "--partition", help="With --backend slurm: the Slurm partition.")
TIME_MIN = typer.Option(240, "--time", help="With --backend slurm: each job's time limit in minutes.")
RUN_THREADS = typer.Option(
    None,
    "--threads",
    min=1,
    help="Threads of each run (default: the CPUs available to this process / --jobs, "
    "so 1 with the default --jobs: runs in parallel processes use the cores better than threads, docs/speed.md).",
)


def _sweep_setup(jobs: int | None, threads: int | None, backend: str) -> tuple[int, int]:
    """(jobs, threads per run) of a command that runs many cells: the defaults of ``reproduce``."""
    from diffcontact.threads import available_cpus, default_jobs

    jobs = jobs or (default_jobs() if backend == "local" else ALL_AT_ONCE)
    per_run = threads or max(1, available_cpus() // jobs)
    _threads(per_run)  # (this process generates the datasets; each run has its own process)
    return jobs, per_run


def _seed_list(seeds: list[str]) -> list[int]:
    from diffcontact.errors import ConfigError

    try:
        return [int(x) for x in _split(seeds)]
    except ValueError as err:
        raise ConfigError(f"--seeds {seeds}: not integers") from err


@app.command("reproduce")
def reproduce(
    tasks: list[str] = typer.Option(
        [], "--tasks", "-t", help="Tasks, repeated or comma-separated: -t BP5-e -t CP3 or -t BP5-e,CP3 (default: all)."
    ),
    models: list[str] = typer.Option(
        [], "--models", "-m", help="Models, repeated or comma-separated (default: the 4 contact models, 3 baselines)."
    ),
    seeds: list[str] = SEEDS,
    out: str = typer.Option("reproduction", "--out", help="Folder of the runs, figures and report.md."),
    quick: bool = typer.Option(False, "--quick", help="Tiny datasets and one epoch: the pipeline in minutes."),
    jobs: int = JOBS,
    data: str = typer.Option(
        "", "--data", help="Dataset root (default: data, or OUT/data with --quick, --noise or --n-train)."
    ),
    noise: float = typer.Option(
        0.0, "--noise", help="Std of the observation noise on the training and validation chunks (0 = none)."
    ),
    n_train: int = typer.Option(None, "--n-train", min=1, help="Training trajectories of every dataset."),
    backend: str = BACKEND,
    address: str = ADDRESS,
    epochs: int = EPOCHS,
    partition: str = PARTITION,
    time_min: int = TIME_MIN,
    threads: int = RUN_THREADS,
) -> None:
    """Train (or reuse) and evaluate every task x model x seed, then write OUT/report.md beside the published values.

    Resumable: evaluated runs are skipped, an interrupted training continues from its last checkpoint."""
    import sys

    from diffcontact.eval.backends import Backend
    from diffcontact.eval.reproduce import reproduce as run_matrix

    jobs, per_run = _sweep_setup(jobs, threads, backend)
    with _user_errors():
        tasks, models = _split(tasks), _split(models)
        run_matrix(
            tasks, models, _seed_list(seeds), out, quick=quick, jobs=jobs, threads=per_run, data=data or None,
            echo=typer.echo, noise=noise, n_train=n_train,
            backend=Backend(backend, address=address, partition=partition, time_min=time_min), epochs=epochs,
            command=" ".join(["diffcontact", *sys.argv[1:]]),
        )  # fmt: skip


@bench_app.command("near-psd")
def bench_near_psd(
    total: int = typer.Option(100_000, "--n", help="Number of problems."),
    batch: int = typer.Option(1000, help="Problems per solver call."),
    threads: int = THREADS,
    seed: int = typer.Option(0, help="Seed of the random instances."),
) -> None:
    """Stress test: singular PSD effective masses rounded to float32 (every size the tasks use); no failure allowed."""
    _threads(threads)
    from diffcontact.bench.near_psd import run_near_psd_benchmark

    with _user_errors():
        run_near_psd_benchmark(total=total, batch=batch, seed=seed)


@bench_app.command("simulate")
def bench_simulate(
    tasks: list[str] = typer.Option(
        [], "--task", "-t", help="Tasks, by name or task file (default: the 8 benchmark tasks)."
    ),
    n: int = typer.Option(1000, "--n", help="Trajectories per task."),
    steps: int = typer.Option(100, "--steps", help="Frames per trajectory."),
    seed: int = typer.Option(0, help="Seed of the initial conditions."),
    out: str = typer.Option("", help="Also write the table as Markdown to this file."),
    threads: int = THREADS,
) -> None:
    """Wall time of simulating N trajectories x T frames for each task (CM, float64)."""
    from diffcontact.bench.simulate import run_simulation_benchmark

    threads = _threads(threads)
    with _user_errors():
        run_simulation_benchmark(tasks=tasks or None, n=n, steps=steps, threads=threads, seed=seed, out=out or None)


control_app = typer.Typer(
    help="Control through contacts: optimise initial states through the simulator.", no_args_is_help=True
)
app.add_typer(control_app, name="control")


@control_app.command("billiards")
def control_billiards(
    out: str = typer.Option("out/control", "--out", help="Folder of billiards_loss.png, billiards_shot.gif, .json."),
    optimiser: str = typer.Option("lm", "--optimiser", help="lm (Levenberg-Marquardt on x_last(T) - goal) or adam."),
    max_simulations: int = typer.Option(200, "--max-simulations", help="Simulations at most (the published 200)."),
    tol: float = typer.Option(1e-6, "--tol", help="Stop once the last ball is within this distance of the goal (m)."),
    trials: int = typer.Option(8, "--trials", help="lm: step lengths tried per simulation, in one batch."),
    lr: float = typer.Option(0.01, "--lr", help="Adam's learning rate (in units of 0.1 m and 0.1 m/s)."),
    balls: int = typer.Option(11, "--balls", help="Balls on the table (the cue ball and a triangle of balls - 1)."),
    frames: int = typer.Option(0, "--frames", help="Frames simulated (0 = the task's 1024)."),
    search_shots: int = typer.Option(
        256, "--search-shots", help="Global stage: cue lines per round, in one batch (0 = start from the published θ0)."
    ),
    search_rounds: int = typer.Option(3, "--search-rounds", help="Global stage: rounds (simulations)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the search's cue lines."),
    starts: int = typer.Option(4, "--starts", help="lm: search candidates it starts from at once, nearest first."),
    gif: bool = typer.Option(True, help="Write the GIF of the final shot."),
    published: bool = typer.Option(True, help="Also simulate the published final cue state for the loss plot."),
    threads: int = THREADS,
    progress: bool = typer.Option(True, help="Show a progress bar."),
) -> None:
    """Billiards (the paper's): the cue ball's initial position and velocity so that the last ball ends at the goal."""
    _threads(threads)
    from diffcontact.control.run import run_billiards

    with _user_errors():
        r = run_billiards(
            out, balls=balls, frames=frames or None, optimiser=optimiser, max_simulations=max_simulations, tol=tol,
            trials=trials, lr=lr, search_shots=search_shots, search_rounds=search_rounds, seed=seed, starts=starts,
            gif=gif, published=published, echo=typer.echo, progress=progress,
        )  # fmt: skip
    typer.echo(f"billiards: distance {r['final_distance_m']:.3g} m after {r['simulations']} simulations "
               f"({r['trajectories']} shots, {r['steps_accepted']} steps; {r['stop']}), "
               f"cue (p, v) = {[round(t, 5) for t in r['best_theta']]}, "
               f"{r['wall_time_s']:.0f} s -> {out}")  # fmt: skip


@control_app.command("throw")
def control_throw(
    out: str = typer.Option("out/control", "--out", help="Folder of throw_MODE_loss.png, throw_MODE.gif, throw.json."),
    run: str = typer.Option("", "--from", help="Also throw with the properties learned by this training run."),
    mode: list[str] = typer.Option(["hit", "vertical"], "--mode", help="hit (land on the target) and/or vertical."),
    optimiser: str = typer.Option("lm", "--optimiser", help="lm (Levenberg-Marquardt) or adam."),
    max_simulations: int = typer.Option(30, "--max-simulations", help="Simulations at most per optimisation."),
    tol: float = typer.Option(1e-5, "--tol", help="Stop at |residual| <= tol (m for hit, m/s for vertical)."),
    trials: int = typer.Option(1, "--trials", help="lm: step lengths tried per simulation, in one batch."),
    lr: float = typer.Option(0.1, "--lr", help="Adam's learning rate (m/s, rad/s)."),
    gif: bool = typer.Option(True, help="Write the GIFs."),
    threads: int = THREADS,
    progress: bool = typer.Option(True, help="Show a progress bar."),
) -> None:
    """Throwing a disk (the paper's, BD1): land on a target after a bounce, or rebound vertically through spin."""
    _threads(threads)
    from diffcontact.control.run import run_throw

    with _user_errors():
        r = run_throw(
            out, run=run or None, modes=tuple(mode), optimiser=optimiser, max_simulations=max_simulations, tol=tol,
            trials=trials, lr=lr, gif=gif, echo=typer.echo, progress=progress,
        )  # fmt: skip
    for m in mode:
        for key, item in r[m].items():
            extra = item.get("landing_distance_to_true_throw_m")
            extra = "" if extra is None else f", lands {extra * 100:.3g} cm from the true-property throw"
            typer.echo(f"throw {m} ({key} properties): loss {item['best_loss']:.3g} after {item['simulations']} "
                       f"simulations, theta {[round(t, 5) for t in item['best_theta']]}, landing (true physics) "
                       f"{[round(c, 5) for c in item['landings_true_physics'][-1]]}{extra}")  # fmt: skip
    typer.echo(f"-> {out}")


@bench_app.command("train")
def bench_train(
    tasks: list[str] = typer.Argument(None, help="Tasks (default: the 8 benchmark tasks)."),
    models: list[str] = typer.Option(["CM-CD-CLNN"], "--models", "-m", help="Models (repeat the option for several)."),
    batch: int = typer.Option(
        None, "--batch", min=1, help="Chunks per step (default: the task's training batch, 50; the published one 200)."
    ),
    warmup: int = typer.Option(2, help="Untimed steps first."),
    repeats: int = typer.Option(15, help="Timed steps (medians reported)."),
    busy: int = typer.Option(0, "--busy", help="Also time the step beside this many busy processes (started here)."),
    seed: int = typer.Option(0, help="Seed of the data and the initial parameters."),
    out: str = typer.Option("", help="Also write the results as JSON to this file."),
    threads: int = typer.Option(
        1, "--threads", min=1, help="Threads of torch, numba and the contact solver (default 1: as `train` runs)."
    ),
) -> None:
    """Time of one training step (forward, backward, optimiser) per task and model, as `train` makes it with its
    defaults: dynamics, contact model and optimiser, beside the same step with contacts disabled (float32, synthetic
    chunks from the task's simulator)."""
    from diffcontact.bench.train import run_train_benchmark

    _threads(threads)
    with _user_errors():
        run_train_benchmark(
            tasks or None, models, batch=batch, warmup=warmup, repeats=repeats, seed=seed, busy=busy,
            out=out or None, echo=typer.echo,
        )  # fmt: skip


@bench_app.command("memory")
def bench_memory(
    tasks: list[str] = typer.Argument(None, help="Tasks (default: the 8 benchmark tasks)."),
    epochs: int = typer.Option(None, "--epochs", min=1, help="Epochs (default: each task's default training's)."),
    data: str = typer.Option("data", "--data", help="Dataset root (missing datasets are generated there)."),
    out: str = typer.Option("", help="Also write the results as JSON to this file, and the table beside it (.md)."),
    threads: int = typer.Option(1, "--threads", min=1, help="Threads of each training (default 1: as `train` runs)."),
) -> None:
    """Resident memory (RSS) at the end of every epoch of each task's default training, in a fresh process per task;
    flat if it grows by at most 50 MB after epoch 5."""
    from diffcontact.bench.memory import run_memory_benchmark

    _threads(threads)
    with _user_errors():
        run_memory_benchmark(tasks or None, epochs, data=data, out=out or None, threads=threads, echo=typer.echo)


peers_app = typer.Typer(
    help="Peers of the real-data benchmark: a cube in MuJoCo and in Bullet, contact parameters fitted to the tosses.",
    no_args_is_help=True,
)
app.add_typer(peers_app, name="peers")


@peers_app.command("fit")
def peers_fit(
    engine: str = typer.Argument(..., help="mujoco or bullet."),
    source: str = typer.Argument(..., help="The tosses: a ContactNets .npz or a folder of K.pt files."),
    out: str = typer.Option(..., "--out", help="Folder of fitted.json, metrics.json and predictions.npz."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the split, the training tosses' order and CMA-ES."),
    split: tuple[float, float, float] = typer.Option(
        (0.8, 0.1, 0.1), "--split", help="Fractions of the tosses for train, val and test."
    ),
    train_tosses: int = typer.Option(
        None, "--train-tosses", min=1, help="Fit on the first N training tosses in a seeded order (default: all)."
    ),
    budget: int = typer.Option(
        None,
        "--budget",
        min=1,
        help="CMA-ES evaluations at most (over its restarts), each over every training toss (default 1800).",
    ),
    twist: str = typer.Option(
        "fitted",
        "--twist",
        help="Initial state: fitted (a free-flight fit, the one our models start from), recorded (the source's "
        "twist) or poses (one-sided differences of the poses).",
    ),
    centre_of_mass: bool = typer.Option(
        True,
        "--centre-of-mass/--no-centre-of-mass",
        help="Also fit the centre of mass's offset from the box centre (com_x, com_y, com_z: body frame, ±2 cm, "
        "from 0), as our models learn it; --no-centre-of-mass keeps it at the box centre.",
    ),
    jobs: int = typer.Option(
        None,
        "--jobs",
        "-j",
        min=1,
        help="Processes that score CMA-ES's candidates (default: one per available CPU; the result is the same).",
    ),
) -> None:
    """Fit an engine's contact parameters to the training tosses (CMA-ES); score it and its nominal parameters on
    the test tosses."""
    from diffcontact.peers.fit import DEFAULT_BUDGET, run_fit
    from diffcontact.threads import available_cpus

    with _user_errors():
        m = run_fit(engine, source, out, seed=seed, split=split, train_tosses=train_tosses,
                    budget=budget or DEFAULT_BUDGET, twist=twist, echo=typer.echo,
                    centre_of_mass=centre_of_mass, jobs=jobs or available_cpus())  # fmt: skip
    for name in ("fitted", "nominal"):
        r = {k: float("nan") for k in ("position_error_pct", "rotation_error_deg", "penetration_pct")} | m[name]
        typer.echo(f"{engine} {name}: position {r['position_error_pct']:.2f} %, rotation "
                   f"{r['rotation_error_deg']:.2f} deg, penetration {r['penetration_pct']:.3f} % (test)")  # fmt: skip
    typer.echo(f"-> {out}")


def main() -> None:  # pragma: no cover - console entry point
    app()


@bench_app.command("tosses")
def bench_tosses(
    source: str = typer.Argument(..., help="The tosses: a folder of ContactNets K.pt files, an .npz, or 'sample'."),
    out: str = typer.Option("runs/toss_sweep", "--out", help="Folder of the sweep's datasets, runs and tables."),
    sizes: list[int] = typer.Option(
        [8, 16, 32, 64, 128, 256], "--size", "-n", help="Training tosses N (repeat; 0: all of the split's)."
    ),
    methods: list[str] = typer.Option(
        [], "--method", "-m", help="Methods (repeat or comma-separated; default: all seven of the sweep)."
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the split by toss and of the training subsets."),
    epochs: int = EPOCHS,
    jobs: int = JOBS,
    backend: str = BACKEND,
    address: str = ADDRESS,
    partition: str = PARTITION,
    time_min: int = TIME_MIN,
    threads: int = RUN_THREADS,
    tables_only: bool = typer.Option(
        False, "--tables", help="Run nothing: write the tables of the cells scored so far (while the sweep runs)."
    ),
) -> None:
    """The training-size sweep on measured tosses: every method at N training tosses, scored on the same test
    tosses; writes sweep.md, sweep.json and sweep.png (resumes where it stopped)."""
    from diffcontact.eval.backends import Backend
    from diffcontact.eval.toss_sweep import METHODS, toss_sweep

    chosen = tuple(_split(methods)) or METHODS
    unknown = sorted(set(chosen) - set(METHODS))
    if unknown:
        raise typer.BadParameter(f"unknown methods {unknown}; known: {list(METHODS)}")
    jobs, per_run = _sweep_setup(jobs, threads, backend)
    with _user_errors():
        toss_sweep(
            source, out, sizes=tuple(sizes), methods=chosen, seed=seed, epochs=epochs, jobs=jobs, threads=per_run,
            backend=Backend(backend, address=address, partition=partition, time_min=time_min),
            tables_only=tables_only, echo=typer.echo,
        )  # fmt: skip
    typer.echo(f"-> {out}/sweep.md")


@bench_app.command("efficiency")
def bench_efficiency(
    task: str = typer.Argument("Rope200", help="The task (the published curves are the 200-node rope's)."),
    sizes: list[int] = typer.Option(
        list(EFFICIENCY_SIZES), "--size", "-n", help="Training trajectories N (repeat; default: the published ten)."
    ),
    models: list[str] = typer.Option(
        [], "--models", "-m", help="Models, repeated or comma-separated (default: CM-CD-CLNN and the 3 baselines)."
    ),
    seeds: list[str] = SEEDS,
    out: str = typer.Option("runs/efficiency", "--out", help="Folder of the reproductions, one per N, and tables."),
    quick: bool = typer.Option(False, "--quick", help="Short trajectories and one epoch: the pipeline in minutes."),
    jobs: int = JOBS,
    backend: str = BACKEND,
    address: str = ADDRESS,
    epochs: int = EPOCHS,
    partition: str = PARTITION,
    time_min: int = TIME_MIN,
    threads: int = RUN_THREADS,
) -> None:
    """Sample efficiency: the 5-step error of each model against the training trajectories N, one reproduction per
    N, beside the published curves; writes efficiency.md, efficiency.json and efficiency.png (resumes).  Beyond the
    task's default 800 trajectories a cell trains its default run's optimiser steps (fewer epochs), unless --epochs."""
    import sys

    from diffcontact.eval.backends import Backend
    from diffcontact.eval.efficiency import MODELS, run_efficiency

    jobs, per_run = _sweep_setup(jobs, threads, backend)
    with _user_errors():
        run_efficiency(
            task, tuple(_split(models)) or MODELS, sizes, out, seeds=_seed_list(seeds), jobs=jobs, threads=per_run,
            backend=Backend(backend, address=address, partition=partition, time_min=time_min), epochs=epochs,
            quick=quick, echo=typer.echo, command=" ".join(["diffcontact", *sys.argv[1:]]),
        )  # fmt: skip
    typer.echo(f"-> {out}/efficiency.md")


if __name__ == "__main__":  # pragma: no cover
    app()
