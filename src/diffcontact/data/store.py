"""Dataset storage: one folder per task, one ``.npz`` per split, a ``meta.json`` with checksums.

Layout of ``<root>/<task>/``:
- ``train.npz``, ``val.npz``, ``test.npz`` with arrays (N trajectories, T frames, L chunk frames, P points, d dims)
  x, v (N, T, P, d) float64 in m and m/s; contact (N, T) bool (an impulse was applied at that frame);
  t (T,) in s; chunk_start (N,) int64; chunk_x, chunk_v (N, L, P, d) (with noise, if any);
  chunk_collision (N,) bool;
- ``meta.json``: the generation request (task config, sizes, seeds, noise, ...), versions, and per split the file's
  SHA-256, array shapes and dtypes, collision counts and time taken. It is written last, so a folder without it
  is an incomplete dataset.

Every file is written through :mod:`diffcontact.files` (a temporary name in the same folder, then renamed).
Loading checks the checksum, the recorded shapes and the task config, and raises :class:`DatasetError` on any
mismatch.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diffcontact.config import TaskConfig, load_task
from diffcontact.errors import ConfigError, DatasetError
from diffcontact.files import TMP_PREFIX, sha256, write_json

FORMAT = 1
META = "meta.json"
SPLITS = ("train", "val", "test")
ARRAYS = ("x", "v", "contact", "t", "chunk_start", "chunk_x", "chunk_v", "chunk_collision")


@dataclass(frozen=True)
class Split:
    """One split as torch tensors (shapes as in the module docstring); ``dt`` in s."""

    name: str
    task: str
    dt: float
    x: torch.Tensor
    v: torch.Tensor
    contact: torch.Tensor
    t: torch.Tensor
    chunk_start: torch.Tensor
    chunk_x: torch.Tensor
    chunk_v: torch.Tensor
    chunk_collision: torch.Tensor

    @property
    def n(self) -> int:
        return int(self.x.shape[0])

    @property
    def chunk_t(self) -> torch.Tensor:
        """Times of the chunk frames relative to the chunk start: (L,) in s."""
        return self.t[: self.chunk_x.shape[1]] - self.t[0]


def save_meta(folder: str | Path, meta: dict[str, Any]) -> None:
    """Write ``meta.json`` atomically."""
    write_json(Path(folder) / META, meta, sort_keys=True)


def remove_stale(folder: str | Path) -> None:
    """Invalidate a dataset before regenerating it: delete ``meta.json`` and leftover temporary files."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    (folder / META).unlink(missing_ok=True)
    for tmp in folder.glob(f"{TMP_PREFIX}*"):
        tmp.unlink(missing_ok=True)


def dataset_folder(root: str | Path, task: str) -> Path:
    """The folder of ``task``'s dataset under ``root``: ``root`` itself if it holds a dataset of that task (an
    imported one, e.g. ``--data data/CubeToss``), else ``root/task`` (``diffcontact generate --out root``)."""
    root = Path(root)
    meta = root / META
    if meta.is_file():
        try:
            if json.loads(meta.read_text()).get("request", {}).get("task") == task:
                return root
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
            pass  # (load_meta reports it, on the folder it is given)
    return root / task


def load_meta(folder: str | Path) -> dict[str, Any]:
    """The parsed ``meta.json`` of a dataset folder (DatasetError if missing, unreadable or of another format)."""
    path = Path(folder) / META
    if not path.is_file():
        raise DatasetError(
            f"{path} is missing: {folder} is not a complete dataset (never generated, or generation was "
            "interrupted); run `diffcontact generate`"
        )
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(f"{path} is not valid JSON: {err}") from err
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DatasetError(f"{path}: format {meta.get('format') if isinstance(meta, dict) else None!r} != {FORMAT}")
    _check_meta(meta, path)
    return meta


# The entries of meta.json that loading reads, by table: a dataset whose metadata lacks one is incomplete.
_REQUEST_KEYS = ("task", "config", "dt", "frames")
_SPLIT_KEYS = ("file", "sha256", "arrays")


def _check_meta(meta: dict[str, Any], path: Path) -> None:
    """DatasetError naming the first entry of ``meta`` that loading needs and that is missing or malformed, or a
    split ``file`` that is not a plain file name in the dataset's folder."""

    def need(table: Any, keys, where: str) -> None:
        if not isinstance(table, dict):
            raise DatasetError(f"{path}: {where} is not a table; the dataset is incomplete, regenerate it")
        for key in keys:
            if key not in table:
                raise DatasetError(f"{path}: {where} lacks {key!r}; the dataset is incomplete, regenerate it")

    need(meta, ("request", "splits"), "the metadata")
    need(meta["request"], _REQUEST_KEYS, "request")
    need(meta["splits"], (), "splits")
    for split, info in meta["splits"].items():
        need(info, _SPLIT_KEYS, f"splits.{split}")
        need(info["arrays"], ARRAYS, f"splits.{split}.arrays")
        for key in ARRAYS:
            need(info["arrays"][key], ("shape", "dtype"), f"splits.{split}.arrays.{key}")
        name = info["file"]
        if not isinstance(name, str) or name in ("", ".", "..") or Path(name).name != name or "\\" in name:
            raise DatasetError(f"{path}: splits.{split}.file = {name!r} is not a file name in the dataset's folder")


def config_json(config: TaskConfig) -> Any:
    """The task config as recorded in the metadata (the parsed TOML through a JSON round trip), without the
    ``[training]`` table, which does not change the data."""
    data_part = {k: v for k, v in config.raw.items() if k != "training"}
    return json.loads(json.dumps(data_part, sort_keys=True, default=str))


def check_config(meta: dict[str, Any], config: TaskConfig | None, folder: str | Path) -> None:
    """DatasetError unless the dataset was generated from ``config`` (default: the current task file)."""
    name = meta["request"]["task"]
    if config is None:
        try:
            config = load_task(name)
        except ConfigError as err:
            raise DatasetError(f"{folder}: cannot verify the config of task {name!r}: {err}") from err
    if config_json(config) != meta["request"]["config"]:
        raise DatasetError(
            f"{folder} was generated from a different config of task {name!r} than the current one "
            f"({config.name}); regenerate it with `diffcontact generate {config.name}`"
        )


def verify_file(folder: str | Path, split: str, meta: dict[str, Any]) -> Path:
    """Check that the split's file exists and has the recorded SHA-256; returns its path."""
    if split not in SPLITS:
        raise DatasetError(f"split = {split!r} is not one of {list(SPLITS)}")
    info = meta["splits"].get(split)
    if info is None:
        raise DatasetError(f"{folder}: split {split!r} is not recorded in {META}")
    path = Path(folder) / info["file"]
    if not path.is_file():
        raise DatasetError(f"{path} is missing")
    digest = sha256(path)
    if digest != info["sha256"]:
        raise DatasetError(
            f"{path}: SHA-256 {digest[:16]}… does not match the recorded {info['sha256'][:16]}…: the file was "
            "modified, truncated or replaced; regenerate the dataset"
        )
    return path


def verify_dataset(folder: str | Path, config: TaskConfig | None = None) -> dict[str, Any]:
    """Check metadata, config and every split's checksum; returns the metadata."""
    meta = load_meta(folder)
    check_config(meta, config, folder)
    for split in meta["splits"]:
        verify_file(folder, split, meta)
    return meta


def load_split(
    folder: str | Path,
    split: str,
    config: TaskConfig | None = None,
    dtype=None,
    task: str | None = None,
    trajectories: bool = True,
) -> Split:
    """Load a verified split (checksum, config, array names, shapes, dtypes) as tensors, cast to ``dtype``
    (floating arrays only; default: as stored, float64); ``task``: the task it must be of (DatasetError if not).
    ``trajectories=False``: the chunks only, x and v left unread (0 frames each: what training reads of a split,
    a twentieth of a 100-frame split's memory)."""
    meta = load_meta(folder)
    if task is not None and meta["request"]["task"] != task:
        raise DatasetError(f"{folder} holds a dataset of task {meta['request']['task']!r}, not {task!r}")
    check_config(meta, config, folder)
    path = verify_file(folder, split, meta)
    info = meta["splits"][split]
    tensors = {}
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as data:  # (np.load leaks its own handle
            for key in ARRAYS:  # on a corrupt file)
                want = info["arrays"][key]
                if not trajectories and key in ("x", "v"):
                    shape = [want["shape"][0], 0, *want["shape"][2:]]
                    tensors[key] = torch.empty(shape, dtype=dtype or getattr(torch, want["dtype"]))
                    continue
                arr = data[key]
                if list(arr.shape) != want["shape"] or str(arr.dtype) != want["dtype"]:
                    raise DatasetError(
                        f"{path}: array {key} is {arr.dtype}{list(arr.shape)}, recorded {want['dtype']}{want['shape']}"
                    )
                t = torch.from_numpy(arr)  # (cast one array at a time: at most one stored copy beside the cast ones)
                tensors[key] = t.to(dtype) if dtype is not None and t.is_floating_point() else t
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as err:
        raise DatasetError(f"{path} is corrupt or incomplete: {err}") from err
    return Split(name=split, task=meta["request"]["task"], dt=float(meta["request"]["dt"]), **tensors)


def describe(arrays: dict[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """Shapes and dtypes of arrays, as recorded in the metadata."""
    return {k: {"shape": list(a.shape), "dtype": str(a.dtype)} for k, a in arrays.items()}
