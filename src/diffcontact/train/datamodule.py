"""Lightning data module over a generated dataset (``diffcontact generate``)."""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader

from diffcontact.config import TaskConfig, load_task
from diffcontact.data.dataset import ChunkDataset, PairDataset, TrajectoryDataset
from diffcontact.data.store import SPLITS, Split, dataset_folder, load_split
from diffcontact.errors import ConfigError

MODES = ("chunks", "pairs")


class ContactDataModule(pl.LightningDataModule):
    """Serves 5-frame chunks (``mode="chunks"``, the CM/CMr models) or one-step pairs (``mode="pairs"``, the
    baselines) of ``<root>/<task>/``, cast to ``dtype`` (float32 by default, as the published training), plus
    the full trajectories for evaluation (:meth:`trajectories`). The training order is shuffled from ``seed``.
    """

    def __init__(
        self,
        task: str | TaskConfig,
        root: str | Path = "data",
        batch_size: int = 200,
        mode: str = "chunks",
        dtype: torch.dtype = torch.float32,
        seed: int = 0,
        num_workers: int = 0,
    ):
        super().__init__()
        if mode not in MODES:
            raise ConfigError(f"mode = {mode!r} is not one of {list(MODES)}")
        if batch_size < 1:
            raise ConfigError(f"batch_size = {batch_size} is not >= 1")
        # (a packaged task's name, a task file's path or the config parsed from it: its data are in root/NAME)
        self.config = task if isinstance(task, TaskConfig) else load_task(task)
        self.folder = dataset_folder(root, self.config.name)
        self.batch_size, self.mode, self.dtype = batch_size, mode, dtype
        self.seed, self.num_workers = seed, num_workers
        self.splits: dict[str, Split] = {}  # (their chunks; x and v of 0 frames: ``load_split(trajectories=False)``)

    def setup(self, stage: str | None = None) -> None:
        """Load and verify (checksum, config) every split's chunks once."""
        for name in SPLITS:
            if name not in self.splits:
                self.splits[name] = self._load(name, trajectories=False)

    def _load(self, name: str, trajectories: bool) -> Split:
        return load_split(self.folder, name, self.config, self.dtype, self.config.name, trajectories=trajectories)

    def _dataset(self, name: str):
        self.setup()
        return (ChunkDataset if self.mode == "chunks" else PairDataset)(self.splits[name])

    def batches_per_epoch(self, processes: int = 1) -> int:
        """Optimiser steps an epoch takes: batches of the training split on each of ``processes`` processes."""
        return -(-len(self._dataset("train")) // (self.batch_size * processes))

    def train_dataloader(self) -> DataLoader:
        gen = torch.Generator().manual_seed(self.seed)
        return DataLoader(
            self._dataset("train"), self.batch_size, shuffle=True, generator=gen, num_workers=self.num_workers
        )

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self._dataset("val"), self.batch_size, num_workers=self.num_workers)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(self._dataset("test"), self.batch_size, num_workers=self.num_workers)

    def trajectories(self, split: str = "test", frames: int | None = None) -> TrajectoryDataset:
        """Full trajectories of a split (e.g. ``frames=50`` for the evaluation rollouts), read from its file."""
        if split not in SPLITS:
            raise ConfigError(f"split = {split!r} is not one of {list(SPLITS)}")
        return TrajectoryDataset(self._load(split, trajectories=True), frames)
