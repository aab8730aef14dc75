"""The training-size sweep on measured tosses (the ContactNets protocol): every method trained on N = 8 … 256
training tosses of one seeded split and scored on the same test tosses with the same metric code.

Methods: the contact models and the paper's baselines (``diffcontact train``), the task's nominal values in the
exact model (no training), and the MuJoCo and Bullet cubes fitted by CMA-ES (``diffcontact peers fit``, optional
extra ``peers``). The sweep resumes: a cell whose metrics.json exists is read, not run again, and a trained cell
resumes from its last checkpoint. Trained cells go to the backend of ``reproduce`` (this machine, Ray or Slurm).
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from diffcontact.data.store import load_meta
from diffcontact.errors import DiffContactError
from diffcontact.eval.backends import Backend
from diffcontact.files import versions, write_json, write_text
from diffcontact.run_dir import METRICS as METRICS_FILE
from diffcontact.run_dir import PREDICTIONS, RunDir

SIZES = (8, 16, 32, 64, 128, 256)
METHODS = ("CM-CD-CLNN", "CMr-CD-CLNN", "MLP-CD-CLNN", "IN-CP-CLNN", "mujoco", "bullet", "nominal")
PEERS = ("mujoco", "bullet")
REFERENCE = "CM-CD-CLNN"  # the method the others are set against, toss by toss
DIVERGED = 1e4  # % of the width: a cell's mean position error at or above this is a rollout that left the data
METRICS = {
    "position_error_pct": "position error (% of the width)",
    "rotation_error_deg": "rotation error (degrees)",
    "penetration_pct": "penetration (% of the width)",
    "same_final_face": "test tosses whose last predicted frame rests on the recorded face",
}


def _dataset(source, out: Path, n: int | None, seed: int, split, task: str) -> Path:
    """The imported dataset of N training tosses (all with None), made once (again where the importer's first
    states have changed since)."""
    from diffcontact.data.measured import first_state_settings, import_tosses

    folder = out / "data" / (f"N{n}" if n else "all") / task
    try:
        request = load_meta(folder)["request"]
        made = (request["seed"], request["split"], request["train_tosses_requested"], request.get("first_state"))
        if made == (seed, list(split), n, first_state_settings()):
            return folder
    except (DiffContactError, KeyError):  # (missing, incomplete or of an older version: import it again)
        pass
    import_tosses(source, folder, task=task, split=split, seed=seed, train_tosses=n)
    return folder


def _imported(out: Path, n: int | None, task: str) -> Path | None:
    """The dataset of N training tosses if the sweep has imported it, else None."""
    folder = out / "data" / (f"N{n}" if n else "all") / task
    return folder if (folder / "meta.json").is_file() else None


def _folders(out: Path, method: str, n: int | None) -> tuple[Path, Path]:
    """Where a method's cell at N lives: its run (or fit) folder, and the folder of its metrics.json and
    predictions.npz (a run's eval/, a peer's own folder)."""
    label = f"N{n}" if n else "all"
    if method == "nominal":
        run = out / "runs" / "nominal"
    elif method in PEERS:
        return out / "peers" / label / method, out / "peers" / label / method
    else:
        run = out / "runs" / label / method
    return run, RunDir(run).eval_dir()


def _cell(
    source, out: Path, method: str, n: int | None, folder: Path, seed: int, split, epochs, task, run_cell
) -> None:
    """Run one method at one training size: its metrics.json (and predictions.npz) written, or an error raised.
    A trained method is a cell of ``reproduce`` (``run_cell``: on this machine, Ray or Slurm, in its own process,
    resuming from its last checkpoint); the nominal values and the peers are scored here."""
    from diffcontact.eval.evaluate import evaluate_nominal
    from diffcontact.eval.reproduce import Cell

    run, _ = _folders(out, method, n)
    if method == "nominal":
        evaluate_nominal(task, folder, RunDir(run).eval_dir(), pictures=False)
    elif method in PEERS:
        from diffcontact.peers.fit import run_fit

        run_fit(method, source, run, seed=seed, split=split, train_tosses=n)
    else:
        todo = "evaluate" if RunDir(run).learned.is_file() else "train"
        record = run_cell(Cell(task, method, 0, run, todo, epochs=epochs, pictures=False), folder, False)
        if record["status"] != "done":
            raise DiffContactError(record.get("error", "failed"))


def _fitted(result: dict) -> dict:
    """The metrics of a cell (a peer's metrics.json holds its fitted and nominal ones)."""
    return result.get("fitted", result)


def toss_sweep(
    source: str | Path,
    out: str | Path,
    *,
    sizes: tuple[int, ...] = SIZES,
    methods: tuple[str, ...] = METHODS,
    seed: int = 0,
    split: tuple[float, float, float] = (0.8, 0.1, 0.1),
    epochs: int | None = None,
    task: str = "CubeToss",
    jobs: int = 1,
    threads: int = 1,
    backend: Backend | None = None,
    tables_only: bool = False,
    echo=print,
) -> dict:
    """Run (or resume) the sweep into ``out`` and write ``out``/sweep.json, sweep.md (the tables) and sweep.png
    (position error against N, one line per method). ``sizes``: numbers of training tosses (0: all of the split's);
    ``epochs``: training epochs (default: the task's); ``jobs`` cells at a time, the trained ones on ``backend``
    (default: this machine) with ``threads`` threads each. A cell that fails leaves the others running; the tables
    are written with it marked, then DiffContactError names it. ``tables_only``: run nothing (no import either),
    write the tables of the cells scored so far, "–" for the others (while the sweep runs, or after it stopped).
    Returns the table {method: {N: metrics}}."""
    from diffcontact.eval.backends import cell_runner

    out = Path(out)
    folders: dict[int, Path | None] = {
        n: _imported(out, n or None, task) if tables_only else _dataset(source, out, n or None, seed, split, task)
        for n in sizes
    }
    todo: dict[Path, tuple[int, str]] = {}  # (by the folder it writes: the nominal cell serves every N)
    for n in sizes:
        for method in methods:
            scored = _folders(out, method, n or None)[1]
            if not (scored / METRICS_FILE).is_file():
                todo.setdefault(scored, (n, method))
    unscored = [f"N{n or 'all'} {m}" for n, m in todo.values()]
    if tables_only:
        if unscored:
            echo(f"{len(unscored)} cells not scored yet: " + ", ".join(unscored))
        todo = {}
    run_cell = cell_runner(backend or Backend(), out, threads) if todo else None  # (--tables: no engine started)
    failed: dict[str, str] = {}

    def job(n: int, method: str) -> None:
        label = f"N{n or 'all'} {method}"
        started, folder = time.perf_counter(), folders[n]
        assert folder is not None  # (imported above: cells run only without tables_only)
        try:
            _cell(source, out, method, n or None, folder, seed, split, epochs, task, run_cell)
        except Exception as err:  # (a failed cell, or a cluster's job lost: the other cells go on)
            failed[label] = f"{type(err).__name__}: {err}"
            echo(f"{label}: failed ({failed[label]})")
            return
        result = _fitted(json.loads((_folders(out, method, n or None)[1] / METRICS_FILE).read_text()))
        seconds = time.perf_counter() - started
        echo(f"{label}: position error {_number(result['position_error_pct'])} % ({seconds:.0f} s)")

    if todo:
        echo(f"{len(todo)} cells to run, {min(jobs, len(todo))} at a time")
        with ThreadPoolExecutor(max_workers=max(1, min(jobs, len(todo)))) as pool:
            for future in [pool.submit(job, *cell) for cell in todo.values()]:
                future.result()
    table: dict[str, dict[str, dict]] = {m: {} for m in methods}
    paired: dict[str, dict[str, dict]] = {m: {} for m in methods if m != REFERENCE}
    for n in sizes:
        key = str(n or "all")
        done = set()
        for method in methods:
            metrics = _folders(out, method, n or None)[1] / METRICS_FILE
            if metrics.is_file():
                table[method][key] = _fitted(json.loads(metrics.read_text()))
                done.add(method)
        folder = folders[n]
        if REFERENCE in done and folder is not None:
            for method, difference in _paired(out, folder, sorted(done), n or None).items():
                paired[method][key] = difference
    record = {"source": str(source), "seed": seed, "split": list(split), "sizes": list(sizes), "epochs": epochs}
    record["cells_not_scored"] = unscored if tables_only else []
    write_json(
        out / "sweep.json", {"table": table, "paired": paired, "failed": failed, **record, "versions": versions()}
    )
    write_text(out / "sweep.md", sweep_markdown(table, paired))
    sweep_figure(table, out / "sweep.png")
    if failed:
        raise DiffContactError(
            f"{len(failed)} cells of the sweep failed: " + "; ".join(f"{k}: {v}" for k, v in failed.items())
        )
    return table


def _paired(out: Path, folder: Path, methods, n: int | None) -> dict[str, dict]:
    """At one N: the exact model's per-toss position error minus each other method's, on the same test tosses
    (``pose_metrics.paired_difference``), from the cells' predictions.npz."""
    from diffcontact.eval.tosses import paired_position_errors

    def path(method: str) -> Path:
        return _folders(out, method, n)[1] / PREDICTIONS

    others = {m: path(m) for m in methods if m != REFERENCE}
    return paired_position_errors(folder, path(REFERENCE), others)


def sweep_markdown(table: dict[str, dict[str, dict]], paired: dict[str, dict[str, dict]] | None = None) -> str:
    """The sweep's tables: one per metric, methods as rows and training sizes as columns; "–" where not measured;
    then the exact model's paired difference to each method, with its 95 % interval."""
    sizes = sorted(
        {k for cells in table.values() for k in cells}, key=lambda k: (k == "all", 0 if k == "all" else int(k))
    )
    lines = []
    for metric, title in METRICS.items():
        lines += [f"**{title}** (`{metric}`)", "", "| method | " + " | ".join(f"N = {k}" for k in sizes) + " |"]
        lines.append("| --- |" + " --- |" * len(sizes))
        for method, cells in table.items():
            vals = [_number(cells[k].get(metric)) if k in cells else "–" for k in sizes]
            lines.append(f"| {method} | " + " | ".join(vals) + " |")
        lines.append("")
    if paired:
        lines += [
            f"**{REFERENCE} minus each method**: position error (% of width), the mean over the test tosses of the "
            "paired difference, and its 95 % bootstrap interval (negative: the exact model is better; an interval "
            "that holds 0 does not separate the two)",
            "",
            "| method | " + " | ".join(f"N = {k}" for k in sizes) + " |",
            "| --- |" + " --- |" * len(sizes),
        ]
        for method, cells in paired.items():
            vals = [_interval(cells[k]) if k in cells else "–" for k in sizes]
            lines.append(f"| {method} | " + " | ".join(vals) + " |")
        lines.append("")
    return "\n".join(lines)


def _diverged(value: float) -> bool:
    """A mean error (% of the width) of rollouts that left the data: not finite, or at least ``DIVERGED``."""
    return not (np.isfinite(value) and abs(value) < DIVERGED)


def _interval(d: dict) -> str:
    if any(_diverged(d[k]) for k in ("mean", "lo", "hi")):
        return "diverged"
    return f"{d['mean']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}]"


def _number(value: float | None) -> str:
    if value is None:  # (a metric that the cell's metrics.json does not hold)
        return "not recorded"
    if isinstance(value, int):  # (a count: the tosses that end on the recorded face)
        return str(value)
    return f"{value:.2g} (diverged)" if _diverged(value) else f"{value:.2f}"


def figure_points(table: dict[str, dict[str, dict]]) -> dict[str, tuple[list, list]]:
    """Per method, the (N, position error %) points of the cells scored, sorted by N, and the N of its cells that
    diverged (``_diverged``): those are drawn as marks, not values."""
    out = {}
    for method, cells in table.items():
        scored = sorted((int(k), c["position_error_pct"]) for k, c in cells.items() if k != "all")
        out[method] = ([(n, e) for n, e in scored if not _diverged(e)], [n for n, e in scored if _diverged(e)])
    return out


def sweep_figure(table: dict[str, dict[str, dict]], path: Path) -> Path:
    """Position error (% of the width) against the number of training tosses, one line per method; the cells of a
    method that diverged as crosses along the top edge."""
    from diffcontact.eval.plots import _pyplot
    from diffcontact.files import save_figure

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    points = figure_points(table)
    scored = [e for kept, _ in points.values() for _, e in kept] or [1.0]
    top = 1.15 * max(scored)
    marks = 0  # (each diverged method's crosses at its own height below the top edge)
    for method, (kept, diverged) in points.items():
        colour = None
        if kept:
            (line,) = ax.plot(*np.array(kept).T, marker="o", label=method)
            colour = line.get_color()
        if diverged:
            marks += 1
            ax.plot(diverged, [(1 - 0.035 * marks) * top] * len(diverged), "x", color=colour, ms=8,
                    label=f"{method}: diverged")  # fmt: skip
    ax.set_ylim(0.8 * min(scored), top)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("training tosses N")
    ax.set_ylabel("position error on the test tosses (% of the width)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path
