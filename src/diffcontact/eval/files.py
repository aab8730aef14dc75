"""Atomic outputs of the evaluation (a temporary file in the same folder, then a rename: an interrupted evaluation
leaves no half-written file), through :func:`diffcontact.data.store.atomic_write`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from diffcontact.data.store import atomic_write


def write_json(path: str | Path, obj) -> Path:
    """``obj`` as indented JSON."""
    atomic_write(Path(path), lambda fh: fh.write((json.dumps(obj, indent=2) + "\n").encode()))
    return Path(path)


def write_text(path: str | Path, text: str) -> Path:
    """UTF-8 text."""
    atomic_write(Path(path), lambda fh: fh.write(text.encode()))
    return Path(path)


def save_npz(path: str | Path, **arrays) -> Path:
    """Arrays into a compressed .npz."""
    atomic_write(Path(path), lambda fh: np.savez_compressed(fh, **{k: np.asarray(a) for k, a in arrays.items()}))
    return Path(path)


def save_figure(fig, path: str | Path, dpi: int) -> Path:
    """A matplotlib figure as PNG."""
    atomic_write(Path(path), lambda fh: fig.savefig(fh, format="png", dpi=dpi))
    return Path(path)


def save_gif(path: str | Path, frames: list[np.ndarray], seconds_per_frame: float) -> Path:
    """RGB frames (H, W, 3) uint8 as a looping GIF."""
    import imageio.v2 as imageio

    atomic_write(Path(path), lambda fh: imageio.mimsave(fh, frames, format="GIF", duration=seconds_per_frame, loop=0))
    return Path(path)
