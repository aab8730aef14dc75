"""Sample efficiency (the paper's analysis on the 200-node rope): the 5-step error of each model against the number
of training trajectories N, set beside the published curves.

One reproduction per N (``OUT/N<N>``: its datasets with N training trajectories, the same validation and test
trajectories for every N, its runs and report), then ``OUT/efficiency.json``, ``efficiency.md`` (the table) and
``efficiency.png`` (log-log, the published curves dashed).  A cell already done is not run again, so the command
resumes where it stopped, and the cells go to the backend of ``reproduce`` (this machine, Ray or Slurm).

Every cell trains with its model's defaults, except that beyond the task's default number of training trajectories
(800) its epochs shrink in proportion (:func:`cell_epochs`): a cell takes at most the optimiser steps of the model's
default run, so that N = 12,800 costs what N = 800 does, not 16 times as much (docs/results.md, "Sample efficiency").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from diffcontact.data.generate import DEFAULT_SIZES
from diffcontact.errors import ConfigError
from diffcontact.eval import published
from diffcontact.eval.backends import Backend
from diffcontact.files import save_figure, versions, write_json, write_text
from diffcontact.run_dir import RunDir

MODELS = ("CM-CD-CLNN", "MLP-CD-CLNN", "IN-CP-CLNN", "IN-CP-SP")  # (the published curves)


def run_efficiency(
    task: str = "Rope200",
    models: Sequence[str] = MODELS,
    sizes: Sequence[int] = published.EFFICIENCY_SIZES,
    out: str | Path = "runs/efficiency",
    *,
    seeds: Sequence[int] = (0,),
    jobs: int = 1,
    threads: int = 1,
    backend: Backend | None = None,
    epochs: int | None = None,
    quick: bool = False,
    echo: Callable[[str], None] = print,
    command: str = "",
) -> dict[str, dict[int, dict | None]]:
    """Train and evaluate every (N, model, seed) not done yet, N in ``sizes`` (training trajectories, each ≥ 1), and
    write the table and figure.  Returns {model: {N: {"mean", "ci95", "seeds"} or None where not measured}}."""
    from diffcontact.eval.reproduce import reproduce

    sizes = _check_sizes(sizes)
    out = Path(out)
    planned: dict[int, dict[str, int | None]] = {}
    for n in sizes:
        planned[n] = {m: epochs or (None if quick else cell_epochs(task, m, n)) for m in models}
        shrunk = "" if epochs else ", ".join(f"{m} {e}" for m, e in planned[n].items() if e is not None)
        note = f" (epochs: {shrunk}, the default run's steps)" if shrunk else ""
        echo(f"N = {n}: {task}, {', '.join(models)}{note}")
        reproduce(
            [task], list(models), list(seeds), out / f"N{n}", jobs=jobs, threads=threads, n_train=n,
            backend=backend, epochs=planned[n], quick=quick, echo=echo, command=command,
        )  # fmt: skip
    table = collect(out, task, models, sizes, seeds)
    record = {
        "task": task, "models": list(models), "sizes": sizes, "seeds": list(seeds), "epochs": epochs,
        "epochs_by_size": {str(n): by_model for n, by_model in planned.items()},  # (None: the model's default)
    }  # fmt: skip
    write_outputs(out, task, table, planned, record)
    return table


def write_outputs(
    out: Path,
    task: str,
    table: dict[str, dict[int, dict | None]],
    epochs: dict[int, dict[str, int | None]],
    record: dict,
) -> None:
    """OUT/efficiency.json (the table, ``record`` and the versions), efficiency.md and efficiency.png; ``epochs``
    {N: {model: epochs or None}} as listed under the table."""
    write_json(out / "efficiency.json", {"table": json_table(table), **record, "versions": versions()})
    write_text(out / "efficiency.md", efficiency_markdown(task, table, epochs))
    efficiency_figure(task, table, out / "efficiency.png")


def cell_epochs(task: str, model: str, n: int, n_default: int = DEFAULT_SIZES["train"]) -> int | None:
    """The epochs of ``model``'s cell with ``n`` training trajectories: None (its default for ``task``) up to
    ``n_default`` trajectories, beyond them ⌈epochs × n_default / n⌉, the optimiser steps of the default run (the
    steps of an epoch grow with n)."""
    from diffcontact.train.config import TrainConfig

    if n <= n_default:
        return None
    return -(-TrainConfig.resolve(task, model).epochs * n_default // n)


def _check_sizes(sizes: Sequence[int]) -> list[int]:
    if not sizes:
        raise ConfigError("sizes: give at least one number of training trajectories")
    for n in sizes:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ConfigError(f"sizes: {n!r} is not a whole number of training trajectories >= 1")
    return sorted({int(n) for n in sizes})


def collect(
    out: Path, task: str, models: Sequence[str], sizes: Sequence[int], seeds: Sequence[int]
) -> dict[str, dict[int, dict | None]]:
    """The 5-step error of every (model, N) from the evaluated runs under ``out``: the mean over seeds of each run's
    mean over test trajectories, with the first seed's 95 % half width (one seed) or 1.96 × the standard error over
    seeds (several); None where no seed's run is evaluated."""
    table: dict[str, dict[int, dict | None]] = {}
    for model in models:
        row: dict[int, dict | None] = {}
        for n in sizes:
            errors = []
            for seed in seeds:
                metrics = RunDir.of_cell(out / f"N{n}", task, model, seed).metrics()
                if metrics and "trajectory_error" in metrics:
                    errors.append(metrics["trajectory_error"])
            if not errors:
                row[n] = None
                continue
            means = [e["mean"] for e in errors]
            half = errors[0]["ci95"] if len(means) == 1 else 1.96 * float(np.std(means, ddof=1)) / len(means) ** 0.5
            row[n] = {"mean": float(np.mean(means)), "ci95": half, "seeds": len(means)}
        table[model] = row
    return table


def json_table(table: dict[str, dict[int, dict | None]]) -> dict:
    """The table as efficiency.json holds it: {model: {str(N): cell or None}}, N in increasing order."""
    return {model: {str(n): row[n] for n in sorted(row)} for model, row in table.items()}


def efficiency_markdown(
    task: str, table: dict[str, dict[int, dict | None]], epochs: dict[int, dict[str, int | None]] | None = None
) -> str:
    """The table: one row per model, one column per N; each cell ours ± its 95 % half width, the published value
    below it where there is one, "not measured" where the run is missing; then the epochs of the cells that did not
    train their model's default ones (``epochs``: {N: {model: epochs or None}})."""
    sizes = sorted({n for row in table.values() for n in row})
    pub = published.SAMPLE_EFFICIENCY.get(task, {})
    lines = [
        f"# Sample efficiency: {task}",
        "",
        "5-step error (sum of the relative errors of frames 0-4, mean over the test trajectories ± the 95 % interval) "
        "against the number N of training trajectories; the published value in brackets.",
        "",
        "| model | " + " | ".join(f"N = {n}" for n in sizes) + " |",
        "|---|" + "---|" * len(sizes),
    ]
    for model, row in table.items():
        cells = []
        for n in sizes:
            cell = row.get(n)
            text = f"{cell['mean']:.3g} ± {cell['ci95']:.2g}" if cell else "not measured"
            if n in pub.get(model, {}):
                text += f" ({pub[model][n]:.3g})"
            cells.append(text)
        lines.append(f"| {model} | " + " | ".join(cells) + " |")
    shrunk = {n: {m: e for m, e in row.items() if e is not None} for n, row in (epochs or {}).items()}
    if any(shrunk.values()):
        lines += [
            "",
            "Epochs other than each model's default (beyond the task's default data: the default run's steps):",
        ]
        lines += [f"- N = {n}: " + ", ".join(f"{m} {e}" for m, e in row.items()) for n, row in shrunk.items() if row]
    return "\n".join(lines) + "\n"


def efficiency_figure(task: str, table: dict[str, dict[int, dict | None]], path: Path) -> Path:
    """Log-log: the 5-step error against N, one line per model (error bars: the 95 % half widths), the published
    curve of each model dashed in its colour."""
    from diffcontact.eval.plots import _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    pub = published.SAMPLE_EFFICIENCY.get(task, {})
    for model, row in table.items():
        pts = sorted((n, c["mean"], c["ci95"]) for n, c in row.items() if c)
        colour = None
        if pts:
            n, mean, half = np.array(pts).T
            (line, *_) = ax.errorbar(n, mean, yerr=half, marker="o", capsize=2, label=model)
            colour = line.get_color()
        if model in pub:
            curve = sorted(pub[model].items())
            ax.plot(*np.array(curve).T, linestyle="--", color=colour, alpha=0.7, label=f"{model} (published)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training trajectories N")
    ax.set_ylabel("5-step rel. error")
    ax.set_title(task, fontsize=9)
    ax.legend(fontsize=6)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path
