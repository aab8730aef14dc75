"""Sample efficiency (the paper's analysis on the 200-node rope): the 5-step error of each model against the number
of training trajectories N, set beside the published curves.

One reproduction per N (``OUT/N<N>``: its datasets with N training trajectories, the same validation and test
trajectories for every N, its runs and report), then ``OUT/efficiency.json``, ``efficiency.md`` (the table) and
``efficiency.png`` (log-log, the published curves dashed).  A cell already done is not run again, so the command
resumes where it stopped, and the cells go to the backend of ``reproduce`` (this machine, Ray or Slurm).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

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
    for n in sizes:
        echo(f"N = {n}: {task}, {', '.join(models)}")
        reproduce(
            [task], list(models), list(seeds), out / f"N{n}", jobs=jobs, threads=threads, n_train=n,
            backend=backend, epochs=epochs, quick=quick, echo=echo, command=command,
        )  # fmt: skip
    table = collect(out, task, models, sizes, seeds)
    record = {"task": task, "models": list(models), "sizes": sizes, "seeds": list(seeds), "epochs": epochs}
    write_json(out / "efficiency.json", {"table": _json_table(table), **record, "versions": versions()})
    write_text(out / "efficiency.md", efficiency_markdown(task, table))
    efficiency_figure(task, table, out / "efficiency.png")
    return table


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


def _json_table(table: dict[str, dict[int, dict | None]]) -> dict:
    return {model: {str(n): cell for n, cell in row.items()} for model, row in table.items()}


def efficiency_markdown(task: str, table: dict[str, dict[int, dict | None]]) -> str:
    """The table: one row per model, one column per N; each cell ours ± its 95 % half width, the published value
    below it where there is one, "not measured" where the run is missing."""
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
