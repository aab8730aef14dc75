"""Noise on chunk frames: its size, and that the holonomic constraints still hold (chain in angle space)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffcontact.data import generate_dataset, load_split
from diffcontact.data.noise import add_noise, noise_kind
from diffcontact.errors import ConfigError
from diffcontact.systems import build_task

CONSTRAINT_TOL = 1e-12  # |Φ|, |J_E v| after noise (m², m, m/s): the projection's stopping rule (measured: 1e-14)
STD = 0.05


def _states(name: str, n: int = 400):
    task = build_task(name)
    state = task.sample(n, seed=3)
    return task, state.x, state.v


@pytest.mark.parametrize(
    ("name", "kind"), [("BP5", "free"), ("Rope", "free"), ("CP3", "chain"), ("BD5", "projected"), ("Gyro", "projected")]
)
def test_noise_keeps_the_constraints(name, kind):
    task, x, v = _states(name)
    cons = task.system.constraints
    assert noise_kind(task.system) == kind
    nx, nv = add_noise(task.system, x, v, STD, torch.Generator().manual_seed(0))
    if cons.count:
        assert float(cons.phi(nx).abs().max()) < CONSTRAINT_TOL
        Jv = cons.jac(nx) @ nv.reshape(nx.shape[0], -1, 1)
        assert float(Jv.abs().max()) < CONSTRAINT_TOL
    dx = (nx - x).flatten(1)
    assert 0.2 * STD < float(dx.std()) < 2 * STD  # noise of the requested size reaches the positions
    if kind == "free":  # i.i.d. N(0, std²) exactly
        assert float(dx.std()) == pytest.approx(STD, rel=0.05)
        assert float((nv - v).std()) == pytest.approx(STD, rel=0.05)


def test_chain_noise_is_gaussian_in_angle_space():
    task, x, v = _states("CP3")
    cons = task.system.constraints
    nx, _ = add_noise(task.system, x, v, STD, torch.Generator().manual_seed(1))

    def angles(p):
        prev = torch.cat([cons.anchors.to(p)[0].expand(p.shape[0], 1, 2), p[:, :-1]], 1)
        link = p - prev
        return torch.atan2(link[..., 0], -link[..., 1])

    dq = torch.remainder(angles(nx) - angles(x) + math.pi, 2 * math.pi) - math.pi
    assert float(dq.std()) == pytest.approx(STD, rel=0.05) and abs(float(dq.mean())) < 0.01


def test_zero_noise_is_an_exact_copy_and_negative_noise_an_error():
    task, x, v = _states("BD5", 4)
    nx, nv = add_noise(task.system, x, v, 0.0, torch.Generator())
    assert torch.equal(nx, x) and torch.equal(nv, v)
    with pytest.raises(ConfigError, match="noise = -1 is not a finite number >= 0"):
        add_noise(task.system, x, v, -1, torch.Generator())
    with pytest.raises(ConfigError, match="noise = 'a' is not a number"):
        add_noise(task.system, x, v, "a", torch.Generator())


def test_generated_noise_is_on_chunks_only_and_recorded(tmp_path):
    small = dict(n_train=8, n_val=4, n_test=4, frames=20, progress=False, echo=None)
    clean = generate_dataset("CP3", tmp_path / "clean", **small)
    noisy = generate_dataset("CP3", tmp_path / "noisy", noise=STD, **small)
    assert noisy["request"]["noise"] == STD and noisy["request"]["noise_kind"] == "chain"
    assert noisy["splits"]["train"]["noise_seed"] is not None and clean["splits"]["train"]["noise_seed"] is None
    a, b = load_split(tmp_path / "clean" / "CP3", "train"), load_split(tmp_path / "noisy" / "CP3", "train")
    assert torch.equal(a.x, b.x) and torch.equal(a.chunk_start, b.chunk_start)  # trajectories stay clean
    assert not np.allclose(a.chunk_x.numpy(), b.chunk_x.numpy())
