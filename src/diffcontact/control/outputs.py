"""Outputs of the control commands, each written atomically (:mod:`diffcontact.files`): loss curves (PNG),
the motion with its target marked (GIF), and a JSON of results, config and versions."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from diffcontact.files import save_figure, save_gif, versions, write_json
from diffcontact.render import draw_2d
from diffcontact.systems.base import System

if TYPE_CHECKING:
    from matplotlib.backends.backend_agg import FigureCanvasAgg


def loss_curves(
    curves: dict[str, list[float]], path: str | Path, title: str, markers: dict[str, dict[int, float]] | None = None
) -> Path:
    """Loss per simulation (log scale) of each curve in ``curves`` ({label: losses}, simulation 1 first), and
    single published points ``markers`` ({label: {simulation: loss}}). PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for label, losses in curves.items():
        y = np.asarray(losses, dtype=float)
        shown = np.isfinite(y)  # (rejected trial steps outside the problem's domain have loss inf)
        ax.semilogy(np.arange(1, len(y) + 1)[shown], y[shown], marker=".", label=label)
    for label, points in (markers or {}).items():
        ax.semilogy(list(points), list(points.values()), "s", mfc="none", ms=7, label=label)
    ax.set_xlabel("simulation (iteration)")
    ax.set_ylabel("loss")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return Path(path)


def motion_gif(
    system: System,
    rows: dict[str, np.ndarray],
    contact: dict[str, np.ndarray],
    target: np.ndarray,
    path: str | Path,
    dt: float,
    every: int = 1,
) -> Path:
    """A GIF of one or more motions side by side: ``rows`` {label: x (T, P, 2)} with their ``contact`` flags (T,),
    the ``target`` (2,) in m drawn as a cross; every ``every``-th frame of length dt (s)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T = min(x.shape[0] for x in rows.values())
    (x0, x1), (y0, y1) = system.drawing.view
    pad = 0.05 * (x1 - x0)
    fig = plt.figure(figsize=(3.3 * len(rows), 3.5), dpi=70)
    frames = []
    for t in range(0, T, every):
        fig.clf()
        for i, (label, x) in enumerate(rows.items()):
            ax = fig.add_subplot(1, len(rows), i + 1)
            draw_2d(ax, system, x[t], bool(contact[label][t]))
            ax.plot(*target, "x", color="tab:red", ms=9, mew=2)
            ax.set_xlim(x0 - pad, x1 + pad)
            ax.set_ylim(y0 - pad, y1 + pad)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(label, fontsize=8)
        fig.suptitle(f"t = {t * dt:.3f} s", fontsize=8)
        fig.canvas.draw()
        frames.append(np.asarray(cast("FigureCanvasAgg", fig.canvas).buffer_rgba())[..., :3].copy())
    plt.close(fig)
    save_gif(path, frames, max(dt * every, 0.02))
    return Path(path)


def write_result(path: str | Path, result: dict) -> Path:
    """``result`` with the package versions, as JSON."""
    return write_json(path, {**result, "versions": versions()})
