"""Render one trajectory to a GIF: bodies to scale, disk and gyroscope orientation, walls and ground."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from diffcontact.files import save_gif
from diffcontact.systems.base import System

if TYPE_CHECKING:
    from matplotlib.backends.backend_agg import FigureCanvasAgg


def _plane_segment(n: np.ndarray, c: float, view) -> np.ndarray:
    """Endpoints (2, 2) of the line n·y + c = 0 clipped to a square around the view box."""
    (x0, x1), (y0, y1) = view
    pad = 0.5 * max(x1 - x0, y1 - y0)
    t = np.array([-n[1], n[0]])
    p = -c * n
    pts = p + np.outer([-10 * pad - 10, 10 * pad + 10], t)
    return pts


def draw_2d(ax, system: System, x: np.ndarray, hit: bool) -> None:
    import matplotlib.patches as mpatches

    draw = system.drawing
    q = system.points_per_body
    anchors = system.anchors.numpy()
    ext = np.concatenate([x, anchors], 0) if len(anchors) else x
    for n, c in zip(draw.plane_normal.numpy(), draw.plane_offset.numpy()):
        seg = _plane_segment(n, float(c), draw.view)
        ax.plot(seg[:, 0], seg[:, 1], color="0.2", lw=2)
    for i, j in draw.segments.tolist():
        ax.plot([ext[i, 0], ext[j, 0]], [ext[i, 1], ext[j, 1]], color="0.4", lw=1.5)
    for a in anchors:
        ax.plot(a[0], a[1], marker="s", color="k", ms=4)
    colors = [
        "tab:blue",
        "tab:orange",
        "tab:green",
        "tab:red",
        "tab:purple",
        "tab:brown",
        "tab:pink",
        "tab:gray",
        "tab:olive",
        "tab:cyan",
    ]
    for b, r in enumerate(draw.radii.tolist()):
        centre = x[b * q]
        ax.add_patch(mpatches.Circle(centre, r, fc=colors[b % len(colors)], ec="k", alpha=0.8))
        if q > 1:  # orientation of a disk: a radius along its first body axis
            tip = centre + r * (x[b * q + 1] - centre)
            ax.plot([centre[0], tip[0]], [centre[1], tip[1]], color="k", lw=1.5)
    if hit:
        ax.set_title("contact", color="tab:red", fontsize=9)


def draw_3d(ax, system: System, x: np.ndarray, hit: bool) -> None:
    """One frame x (P, 3): the planes, then balls (shape "ball") or the gyroscope's disk (shape "disk3d")."""
    draw = system.drawing
    lo, hi = min(v[0] for v in draw.view), max(v[1] for v in draw.view)
    for n, c in zip(draw.plane_normal.numpy(), draw.plane_offset.numpy()):
        # a square patch of the plane n·y + c = 0 through its point closest to the origin
        t1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        s = np.linspace(lo, hi, 2)
        u, w = np.meshgrid(s, s)
        pts = -c * n + u[..., None] * t1 + w[..., None] * t2
        ax.plot_surface(pts[..., 0], pts[..., 1], pts[..., 2], color="0.6", alpha=0.3)
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_zlim(lo, hi)
    if draw.shape == "ball":  # (marker area in points², about to scale for the figure size of render_gif)
        size = (200 * draw.radii.numpy() / (hi - lo)) ** 2
        ax.scatter(x[:, 0], x[:, 1], x[:, 2], s=size, c="tab:red" if hit else "tab:blue", depthshade=True)
        return
    com, e1, e2, e3 = x[0], x[1] - x[0], x[2] - x[0], x[3] - x[0]
    r = float(draw.radii[0])
    a = np.linspace(0, 2 * np.pi, 60)
    rim = com + r * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
    ax.plot(rim[:, 0], rim[:, 1], rim[:, 2], color="tab:red" if hit else "tab:blue", lw=2)
    ax.plot([com[0], rim[0, 0]], [com[1], rim[0, 1]], [com[2], rim[0, 2]], color="k", lw=1)  # spin marker
    anchor = system.anchors.numpy()[0]
    ax.plot([anchor[0], com[0]], [anchor[1], com[1]], [anchor[2], com[2]], color="0.3", lw=2)
    tip = com + 0.3 * e3
    ax.plot([com[0], tip[0]], [com[1], tip[1]], [com[2], tip[2]], color="tab:green", lw=1.5)


def render_gif(system: System, x: np.ndarray, contact: np.ndarray, path: str | Path, dt: float, every: int = 1) -> None:
    """Write a GIF of one trajectory: x (T, P, d) positions, contact (T,) flags; frame time dt in s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d import Axes3D

    frames = []
    fig = plt.figure(figsize=(4, 4), dpi=80)
    for t in range(0, x.shape[0], every):
        fig.clf()
        if system.d == 3:
            ax = fig.add_subplot(projection="3d")
            draw_3d(ax, system, x[t], bool(contact[t]))
        else:
            ax = fig.add_subplot()
            draw_2d(ax, system, x[t], bool(contact[t]))
            (x0, x1), (y0, y1) = system.drawing.view
            pad = 0.05 * (x1 - x0)
            ax.set_xlim(x0 - pad, x1 + pad)
            ax.set_ylim(y0 - pad, y1 + pad)
            ax.set_aspect("equal")
        text = ax.text2D if isinstance(ax, Axes3D) else ax.text  # (3-D axes: system.d == 3)
        text(0.02, 0.95, f"t = {t * dt:.3f} s", transform=ax.transAxes, fontsize=8)
        fig.canvas.draw()
        frames.append(np.asarray(cast("FigureCanvasAgg", fig.canvas).buffer_rgba())[..., :3].copy())
    plt.close(fig)
    save_gif(path, frames, max(dt * every, 0.02))
