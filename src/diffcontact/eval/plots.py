"""Figures of the metrics (PNG): error curves (paper Fig. 4), true energy (Fig. 5) and 5-step error bars (Fig. 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from diffcontact.files import save_figure


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _floor(values, published: float) -> float:
    """The lower limit of a log axis: the published one, lowered to the decade below the smallest positive
    value if that is smaller."""
    positive = [v for v in values if v > 0]
    return min(published, 10.0 ** np.floor(np.log10(min(positive)))) if positive else published


def _grid(n: int):
    """A figure with n panels in rows of up to 4, and the flat list of its axes."""
    plt = _pyplot()
    cols = min(n, 4)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat[:n])


def error_curves(panels: dict[str, dict[str, list[float]]], dts: dict[str, float], path: str | Path) -> Path:
    """Fig. 4: per panel (task) the mean relative error per frame of each model ({task: {model: curve}}), log y
    from 1e-5 (lower where a curve is) to 1e2, against time t·dt (``dts``: {task: dt} in s); a dashed line at 4·dt,
    the training horizon."""
    plt = _pyplot()
    fig, axes = _grid(len(panels))
    for ax, (task, curves) in zip(axes, panels.items()):
        dt = dts[task]
        for model, curve in curves.items():
            t, curve = np.arange(len(curve)) * dt, np.asarray(curve, dtype=float)
            ax.plot(t, np.where(curve > 0, curve, np.nan), label=model, lw=1.2)  # (0, as at frame 0: off a log axis)
        ax.axvline(4 * dt, color="0.5", ls="--", lw=0.8)
        ax.set_yscale("log")
        ax.set_ylim(_floor([v for c in curves.values() for v in c], 1e-5), 1e2)
        _label(ax, task, "rel. error")
    return _save_panels(plt, fig, axes, path)


def _label(ax, title: str, ylabel: str) -> None:
    """A panel's title and axis labels against time, in the small fonts of the report's grids."""
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("t (s)", fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)


def _save_panels(plt, fig, axes, path: str | Path) -> Path:
    """The legend on the first panel, then the figure written (atomically) and closed."""
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return Path(path)


def energy_panels(panels: dict[str, dict[str, list[float]]], dts: dict[str, float], path: str | Path) -> Path:
    """Fig. 5: per panel (task) the true energy along one test trajectory, the truth (key "truth") and each model's
    prediction ({task: {label: energy per frame in J}}), y within ±0.2 J of the true initial energy."""
    plt = _pyplot()
    fig, axes = _grid(len(panels))
    for ax, (task, series) in zip(axes, panels.items()):
        dt = dts[task]
        for label, energy in series.items():
            style = dict(color="k", lw=2.0, ls="--") if label == "truth" else dict(lw=1.2)
            ax.plot(np.arange(len(energy)) * dt, energy, label=label, **style)
        e0 = series["truth"][0]
        ax.set_ylim(e0 - 0.2, e0 + 0.2)
        _label(ax, task, "true energy (J)")
    return _save_panels(plt, fig, axes, path)


def error_bars(
    cells: dict[str, dict[str, tuple[float, float | None]]],
    path: str | Path,
    published: dict[str, dict[str, tuple[float, float]]] | None = None,
) -> Path:
    """Fig. 3: the 5-step error (mean and 95 % half width) of each model, grouped by task ({task: {model: (mean,
    half)}}; a missing cell is left empty), log y from 1e-5 (lower where a bar is) to 30; ``published`` values of
    the same form are black marks on the bars they belong to."""
    plt = _pyplot()
    tasks = list(cells)
    models = list(dict.fromkeys(m for row in cells.values() for m in row))
    width = 0.8 / max(len(models), 1)
    fig, ax = plt.subplots(figsize=(max(4.0, 1.1 * len(tasks) + 1.5), 3.2))
    for j, model in enumerate(models):
        xs, means, halves = [], [], []
        for i, task in enumerate(tasks):
            if model in cells[task]:
                mean, half = cells[task][model]
                xs.append(i + (j - (len(models) - 1) / 2) * width)
                means.append(mean)
                halves.append(half or 0.0)
        ax.bar(xs, means, width, yerr=halves, label=model, capsize=2)
        marks = [(i + (j - (len(models) - 1) / 2) * width, (published or {}).get(t, {}).get(model)) for i, t in
                 enumerate(tasks)]  # fmt: skip
        marks = [(x, pub[0]) for x, pub in marks if pub]
        if marks:
            labelled = any(line.get_label() == "published" for line in ax.get_lines())
            ax.plot(*zip(*marks), "k_", ms=12, mew=2, label=None if labelled else "published")
    ax.set_xticks(range(len(tasks)), tasks, fontsize=8)
    ax.set_yscale("log")
    ax.set_ylim(_floor([m for row in cells.values() for m, _ in row.values()], 1e-5), 30)
    ax.set_ylabel("5-step rel. error", fontsize=8)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return Path(path)
