"""torch Datasets (chunks, one-step pairs, trajectories) and the Lightning data module."""

from __future__ import annotations

import pytest
import torch

from diffcontact.data import generate_dataset, load_split
from diffcontact.data.dataset import ChunkDataset, PairDataset, TrajectoryDataset
from diffcontact.errors import ConfigError, DatasetError
from diffcontact.train.datamodule import ContactDataModule

TASK = "BP5-e"


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    generate_dataset(TASK, root, n_train=10, n_val=4, n_test=4, frames=60, progress=False, echo=None)
    return root


def test_chunk_pair_and_trajectory_datasets(root):
    split = load_split(root / TASK, "train")
    chunks = ChunkDataset(split)
    x, v, t, cld, index = chunks[3]
    assert index == 3 and len(chunks) == 10 and x.shape == v.shape == (5, 5, 2) and cld.dtype == torch.bool
    assert torch.allclose(t, torch.arange(5, dtype=torch.float64) * split.dt)
    s = int(split.chunk_start[3])
    assert torch.equal(x, split.x[3, s : s + 5]) and bool(cld) == bool(split.contact[3, s : s + 5].any())
    pairs = PairDataset(split)
    assert len(pairs) == 10 * 4
    x0, v0, x1, v1, dt, hit = pairs[3 * 4 + 2]  # chunk 3, step 2 -> 3
    assert torch.equal(x0, split.x[3, s + 2]) and torch.equal(v1, split.v[3, s + 3]) and float(dt) == split.dt
    assert bool(hit) == bool(split.contact[3, s + 3])
    traj = TrajectoryDataset(split, frames=50)
    assert len(traj) == 10 and traj[0][0].shape == (50, 5, 2) and traj[0][3].shape == (50,)
    with pytest.raises(ValueError, match=r"frames = 61 is not in \[2, 60\]"):
        TrajectoryDataset(split, frames=61)


def test_datamodule_serves_float32_batches_deterministically(root):
    dm = ContactDataModule(TASK, root, batch_size=4, seed=5)
    dm.setup("fit")
    x, v, t, cld, index = next(iter(dm.train_dataloader()))
    assert x.shape == (4, 5, 5, 2) and x.dtype == torch.float32 and t.shape == (4, 5) and cld.shape == (4,)
    assert torch.equal(x, dm.splits["train"].chunk_x[index])  # (each chunk's index in the split)
    again = ContactDataModule(TASK, root, batch_size=4, seed=5)
    assert torch.equal(next(iter(again.train_dataloader()))[0], x)
    assert sum(b[0].shape[0] for b in dm.val_dataloader()) == 4 and len(dm.test_dataloader().dataset) == 4
    pairs = ContactDataModule(TASK, root, batch_size=8, mode="pairs")
    x0, v0, x1, v1, dt, hit = next(iter(pairs.train_dataloader()))
    assert x0.shape == (8, 5, 2) and dt.dtype == torch.float32
    assert dm.trajectories("test", frames=50)[0][0].shape == (50, 5, 2)
    # training reads the chunks only: the splits it holds have no frames of x and v, the chunks as a full load's
    full = load_split(root / TASK, "train", dtype=torch.float32)
    held = dm.splits["train"]
    assert held.x.shape == held.v.shape == (10, 0, 5, 2) and held.x.dtype == torch.float32 and held.n == 10
    for key in ("chunk_x", "chunk_v", "chunk_start", "chunk_collision", "contact", "t"):
        assert torch.equal(getattr(held, key), getattr(full, key)), key
    assert torch.equal(pairs._dataset("train").x1, PairDataset(full).x1)


def test_datamodule_errors(root, tmp_path):
    with pytest.raises(ConfigError, match="mode = 'steps' is not one of"):
        ContactDataModule(TASK, root, mode="steps")
    with pytest.raises(ConfigError, match="batch_size = 0"):
        ContactDataModule(TASK, root, batch_size=0)
    with pytest.raises(DatasetError, match="not a complete dataset"):
        ContactDataModule(TASK, tmp_path).setup()
