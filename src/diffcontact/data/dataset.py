"""torch Datasets over a stored split (no Lightning here): chunks, one-step pairs, full trajectories."""

from __future__ import annotations

import torch
from torch.utils.data import Dataset

from diffcontact.data.store import Split


class ChunkDataset(Dataset):
    """The split's chunks, one per trajectory. Item i: x, v (L, P, d), t (L,) in s from the chunk start,
    collision () bool (the chunk contains a collision frame), i () (the chunk's index in the split)."""

    def __init__(self, split: Split):
        self.x, self.v, self.collision = split.chunk_x, split.chunk_v, split.chunk_collision
        self.t = split.chunk_t

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, int]:
        return self.x[i], self.v[i], self.t, self.collision[i], i


class PairDataset(Dataset):
    """One-step pairs (z_k, z_{k+1}) of every chunk, for the baselines: N (L − 1) items (800 · 4 = 3200 for the
    benchmark). Item: x0, v0, x1, v1 (P, d), dt () in s, collision () bool (an impulse at frame k + 1)."""

    def __init__(self, split: Split):
        n, L = split.chunk_x.shape[:2]
        self.x0 = split.chunk_x[:, :-1].reshape(n * (L - 1), *split.chunk_x.shape[2:])
        self.v0 = split.chunk_v[:, :-1].reshape(self.x0.shape)
        self.x1 = split.chunk_x[:, 1:].reshape(self.x0.shape)
        self.v1 = split.chunk_v[:, 1:].reshape(self.x0.shape)
        frame = split.chunk_start[:, None] + torch.arange(1, L)  # (N, L − 1): index of z_{k+1}
        self.collision = split.contact.gather(1, frame).reshape(-1)
        self.dt = torch.tensor(split.dt, dtype=split.chunk_x.dtype)

    def __len__(self) -> int:
        return int(self.x0.shape[0])

    def __getitem__(self, i: int):
        return self.x0[i], self.v0[i], self.x1[i], self.v1[i], self.dt, self.collision[i]


class TrajectoryDataset(Dataset):
    """Full noise-free trajectories for evaluation, optionally their first ``frames`` frames (e.g. 50-frame
    rollouts). Item: x, v (T, P, d), t (T,) in s, contact (T,) bool."""

    def __init__(self, split: Split, frames: int | None = None):
        T = split.x.shape[1]
        frames = T if frames is None else frames
        if not 2 <= frames <= T:
            raise ValueError(f"frames = {frames} is not in [2, {T}]")
        self.x, self.v = split.x[:, :frames], split.v[:, :frames]
        self.t, self.contact = split.t[:frames], split.contact[:, :frames]

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def __getitem__(self, i: int):
        return self.x[i], self.v[i], self.t, self.contact[i]
