"""Pictures of motion: a GIF of predicted against true motion, and rollout strips (paper Figs. 7-13).

Bodies are drawn by :mod:`diffcontact.render` (the same drawing as ``diffcontact simulate --gif``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from diffcontact.files import save_figure, save_gif
from diffcontact.render import draw_2d, draw_3d
from diffcontact.systems.base import System

if TYPE_CHECKING:
    from matplotlib.backends.backend_agg import FigureCanvasAgg


def _axes(fig, system: System, rows: int, cols: int, i: int):
    """Subplot ``i`` (1-based) of a rows x cols grid, framed like render.render_gif."""
    if system.d == 3:
        return fig.add_subplot(rows, cols, i, projection="3d")
    return fig.add_subplot(rows, cols, i)


def _draw(ax, system: System, x: np.ndarray, hit: bool) -> None:
    """One frame x (P, d) of ``system`` on ``ax``, axes off."""
    if system.d == 3:
        draw_3d(ax, system, x, hit)
        ax.set_axis_off()
        return
    draw_2d(ax, system, x, hit)
    (x0, x1), (y0, y1) = system.drawing.view
    pad = 0.05 * (x1 - x0)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def rollout_strip(
    system: System, rows: dict[str, np.ndarray], contact: np.ndarray, path: str | Path, dt: float, every: int = 5
) -> Path:
    """A grid of frames 0, every, 2·every, …: one row per trajectory in ``rows`` ({label: x (T, P, d)}, the same
    T; the first row is the truth, whose ``contact`` (T,) flags are shown), one column per shown frame.  PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d import Axes3D

    T = next(iter(rows.values())).shape[0]
    shown = list(range(0, T, every))
    size = 1.1
    fig = plt.figure(figsize=(size * len(shown) + 0.9, size * len(rows) + 0.3))
    for r, (label, x) in enumerate(rows.items()):
        for c, t in enumerate(shown):
            ax = _axes(fig, system, len(rows), len(shown), r * len(shown) + c + 1)
            _draw(ax, system, x[t], bool(contact[t]) if r == 0 else False)
            ax.set_title(f"{t * dt:.2f} s" + (" (contact)" if contact[t] else "") if r == 0 else "", fontsize=7)
            if c == 0:
                text = ax.text2D if isinstance(ax, Axes3D) else ax.text  # (3-D axes: system.d == 3)
                text(-0.08, 0.5, label, transform=ax.transAxes, rotation=90, ha="right", va="center", fontsize=7)
    fig.subplots_adjust(left=0.06, right=0.995, top=0.9, bottom=0.01, wspace=0.03, hspace=0.05)
    save_figure(fig, path, dpi=70, colors=64)
    plt.close(fig)
    return Path(path)


def compare_gif(
    system: System, x_true: np.ndarray, x_pred: np.ndarray, contact: np.ndarray, path: str | Path, dt: float
) -> Path:
    """A GIF of the true (left) and predicted (right) motion side by side: x_true, x_pred (T, P, d), contact (T,)
    the true frames with an impulse; frame time dt in s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = []
    fig = plt.figure(figsize=(6, 3.2), dpi=70)
    for t in range(x_true.shape[0]):
        fig.clf()
        for i, (label, x) in enumerate((("truth (CM)", x_true), ("model", x_pred))):
            ax = _axes(fig, system, 1, 2, i + 1)
            _draw(ax, system, x[t], bool(contact[t]) and i == 0)
            ax.set_title(label, fontsize=9)
        fig.suptitle(f"t = {t * dt:.3f} s", fontsize=9)
        fig.canvas.draw()
        frames.append(np.asarray(cast("FigureCanvasAgg", fig.canvas).buffer_rgba())[..., :3].copy())
    plt.close(fig)
    save_gif(path, frames, max(dt, 0.02))
    return Path(path)
