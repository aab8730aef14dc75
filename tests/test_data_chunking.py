"""Chunk selection (the published rule): usable windows only, the collision share near one half, determinism, errors."""

from __future__ import annotations

import pytest
import torch

from diffcontact.data.chunking import gather_windows, select_chunks
from diffcontact.data.generate import make_split
from diffcontact.errors import DatasetError
from diffcontact.systems import build_task

SHARE_LO, SHARE_HI = 0.4, 0.6  # the spec reports 404-406 of 800 and 49-50 of 100 for these tasks


def _random_contacts(n: int, frames: int, p_traj: float, seed: int) -> torch.Tensor:
    """Synthetic flags: a share p_traj of trajectories collide, in bursts of 1-3 frames; frame 0 never."""
    g = torch.Generator().manual_seed(seed)
    c = torch.rand(n, frames, generator=g) < 0.03
    c |= torch.roll(c, 1, 1) & (torch.rand(n, frames, generator=g) < 0.5)
    c[torch.rand(n, generator=g) >= p_traj] = False
    c[:, 0] = False
    return c


def _check_windows(contact, starts, flags, length):
    win = gather_windows(contact, starts, length)
    assert not win[:, 0].any(), "a chunk starts in a collision frame"
    assert torch.equal(flags, win.any(1))


@pytest.mark.parametrize("p_traj", [1.0, 0.8, 0.55])
def test_share_near_half_when_most_trajectories_collide(p_traj):
    contact = _random_contacts(1000, 100, p_traj, seed=3)
    starts, flags = select_chunks(contact, 5, torch.Generator().manual_seed(0))
    _check_windows(contact, starts, flags, 5)
    assert SHARE_LO <= flags.double().mean() <= SHARE_HI


def test_all_colliding_trajectories_marked_when_few_collide():
    contact = _random_contacts(400, 60, 0.3, seed=5)
    starts, flags = select_chunks(contact, 5, torch.Generator().manual_seed(0))
    _check_windows(contact, starts, flags, 5)
    assert torch.equal(flags, contact.any(1))  # every colliding trajectory gets a colliding chunk


def test_same_seed_same_chunks_and_window_fallbacks():
    contact = _random_contacts(300, 40, 0.9, seed=1)
    a = select_chunks(contact, 5, torch.Generator().manual_seed(7))
    b = select_chunks(contact, 5, torch.Generator().manual_seed(7))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    # no collision-free window (collisions every other frame): a colliding window is taken, never frame 1, 3, ...
    alt = torch.zeros(4, 12, dtype=torch.bool)
    alt[:, 1::2] = True
    starts, flags = select_chunks(alt, 5, torch.Generator().manual_seed(0))
    assert flags.all() and (starts % 2 == 0).all()


def test_no_usable_window_and_bad_arguments_are_errors():
    contact = torch.zeros(3, 10, dtype=torch.bool)
    contact[1] = True  # every frame, including the first, is a collision frame
    with pytest.raises(DatasetError, match=r"trajectories \[1\] have no window of 5 frames"):
        select_chunks(contact, 5, torch.Generator())
    with pytest.raises(DatasetError, match="chunk length = 11"):
        select_chunks(torch.zeros(2, 10, dtype=torch.bool), 11, torch.Generator())
    with pytest.raises(DatasetError, match="bool tensor"):
        select_chunks(torch.zeros(2, 10), 5, torch.Generator())


@pytest.mark.slow
@pytest.mark.parametrize("name", ["BP5-e", "BP5", "CP3-e", "CP3", "BD5", "Gyro-e", "Gyro"])
def test_benchmark_task_chunks_collide_about_half_the_time(name):
    task = build_task(name)
    arrays = make_split(task, 200, seed=11, frames=task.frames, progress=False)
    contact = torch.from_numpy(arrays["contact"])
    starts, flags = torch.from_numpy(arrays["chunk_start"]), torch.from_numpy(arrays["chunk_collision"])
    _check_windows(contact, starts, flags, 5)
    assert SHARE_LO <= flags.double().mean() <= SHARE_HI, (name, float(flags.double().mean()))
