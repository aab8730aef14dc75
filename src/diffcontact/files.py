"""Writing the package's outputs: every file (datasets, runs, evaluations, figures, GIFs, tables) is written by
:func:`atomic_write`, to a temporary name in its folder and then renamed, so an interrupted or failed write leaves
the previous file, never half of one.  Also checksums and the versions an output records."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from diffcontact.errors import ConfigError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

TMP_PREFIX = ".tmp-"


def sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def atomic_write(path: Path, write) -> None:
    """Write through ``write(fh)`` into a temporary file next to ``path``, fsync, then rename onto ``path``; an
    OSError (a full disk, ...) leaves no file behind and is raised again naming ``path``."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{path.name}.", dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except OSError as err:  # (disk full, read-only, ...: the error names the file; OSError(errno) keeps its subclass)
        raise OSError(err.errno, f"cannot write {path}: {err.strerror or err}") from err
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.remove(tmp)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_output(path: str | Path, field: str, folder: bool = False) -> Path:
    """ConfigError unless ``path`` can be written: a file (or with ``folder`` a directory) that is not the other
    kind, below a writable directory (missing folders are made when it is written)."""
    path = Path(path)
    if path.exists() and path.is_dir() != folder:
        raise ConfigError(f"{field} = {str(path)!r} is {'a file' if folder else 'a directory'}; give a "
                          f"{'folder' if folder else 'file'} name")  # fmt: skip
    parent = path.parent if not path.exists() else path
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"{field} = {str(path)!r}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{field} = {str(path)!r}: the folder {parent} is not writable")
    return path


def write_text(path: str | Path, text: str) -> Path:
    """UTF-8 text, atomically."""
    atomic_write(Path(path), lambda fh: fh.write(text.encode()))
    return Path(path)


def write_json(path: str | Path, obj, sort_keys: bool = False) -> Path:
    """``obj`` as indented JSON, atomically."""
    return write_text(path, json.dumps(obj, indent=2, sort_keys=sort_keys) + "\n")


def save_npz(path: str | Path, **arrays) -> Path:
    """Arrays into a compressed .npz, atomically."""
    # (pyright matches the unpacked names against numpy's allow_pickle flag too: none of them is that)
    atomic_write(Path(path), lambda fh: np.savez_compressed(fh, **{k: np.asarray(a) for k, a in arrays.items()}))  # pyright: ignore[reportArgumentType]
    return Path(path)


def save_arrays(path: str | Path, arrays: Mapping[str, ArrayLike]) -> str:
    """Write arrays to ``path`` (.npz, uncompressed) atomically; returns its SHA-256."""
    path = Path(path)
    atomic_write(path, lambda fh: np.savez(fh, **arrays))  # pyright: ignore[reportArgumentType] (as in save_npz)
    return sha256(path)


def save_figure(fig, path: str | Path, dpi: int, colors: int | None = None) -> Path:
    """A matplotlib figure as PNG, atomically; with ``colors``, reduced to a palette of that many colours (a
    third of the size for drawings of a few flat colours, such as the rollout strips)."""
    if colors is None:
        atomic_write(Path(path), lambda fh: fig.savefig(fh, format="png", dpi=dpi))
        return Path(path)
    import io

    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    image = Image.open(buffer).convert("RGB").quantize(colors=colors)
    atomic_write(Path(path), lambda fh: image.save(fh, format="PNG", optimize=True))
    return Path(path)


def save_gif(path: str | Path, frames: list[np.ndarray], seconds_per_frame: float) -> Path:
    """RGB frames (H, W, 3) uint8 as a looping GIF, atomically."""
    import imageio.v2 as imageio

    ims = cast("list[ArrayLike]", frames)  # (imageio asks for a list of ArrayLike, which a list of arrays is not)
    atomic_write(Path(path), lambda fh: imageio.mimsave(fh, ims, format="GIF", duration=seconds_per_frame, loop=0))
    return Path(path)


def versions(**extra: str) -> dict[str, str]:
    """The versions an output records: diffcontact, torch, numpy, python (and ``extra``)."""
    import torch

    from diffcontact import __version__

    base = dict(diffcontact=__version__, torch=torch.__version__, numpy=np.__version__)
    return base | {"python": platform.python_version()} | extra
