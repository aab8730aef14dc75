"""Shared pieces of the system builders: validated coefficients, walls, rigid-body constraints, sampling."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from diffcontact.config import Section, TaskConfig
from diffcontact.dynamics.constraints import Constraints
from diffcontact.errors import ConfigError
from diffcontact.state import State

F64 = torch.float64


def coefficients(cfg: TaskConfig, n_slots: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(μ, e) of shape (n_slots,) from ``contact.mu`` and ``contact.cor``: 1 value (broadcast) or n_slots."""
    sec = cfg.section("contact")
    mu = sec.numbers("mu", length=(1, n_slots), lo=0.0)
    cor = sec.numbers("cor", length=(1, n_slots), lo=0.0, hi=1.0)
    return (torch.tensor(mu, dtype=F64).expand(n_slots).clone(), torch.tensor(cor, dtype=F64).expand(n_slots).clone())


def planes(sec: Section, key: str, d: int, default=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Planes [n_1..n_d, c] meaning n·y + c >= 0 is free, normalised: (normal (W, d), offset (W,))."""
    rows = sec.matrix(key, cols=d + 1, default=default)
    t = torch.tensor(rows, dtype=F64).reshape(-1, d + 1)
    norm = t[:, :d].norm(dim=-1)
    for i, value in enumerate(norm.tolist()):
        if value == 0.0:
            raise ConfigError(f"{sec.prefix}.{key}[{i}] has a zero normal")
    return t[:, :d] / norm[:, None], t[:, d] / norm


def rigid_body_distances(n_bodies: int, d: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Distance constraints keeping each extended body's axes orthonormal: (i, j, length), d(d+1)/2 per body.

    Points of body b are b(d+1) + [0 (centre), 1..d (centre + e_k)]: |e_k| = 1 and |e_j − e_k| = √2.
    """
    local = [(0, k, 1.0) for k in range(1, d + 1)]
    local += [(j, k, math.sqrt(2.0)) for j in range(1, d + 1) for k in range(j + 1, d + 1)]
    base = torch.arange(n_bodies)[:, None] * (d + 1)
    i = (base + torch.tensor([a for a, _, _ in local])).flatten()
    j = (base + torch.tensor([b for _, b, _ in local])).flatten()
    length = torch.tensor([L for _, _, L in local], dtype=F64).repeat(n_bodies)
    return i, j, length


def make_constraints(n_points: int, d: int, anchors: torch.Tensor, dist=None, joints=None) -> Constraints:
    """Constraints from optional (i, j, length) distance tensors and (pts, weights, at) joint tensors."""
    if dist is None:
        dist = (torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=F64))
    if joints is None:
        joints = (torch.zeros(0, 1, dtype=torch.long), torch.zeros(0, 1, dtype=F64), torch.zeros(0, d, dtype=F64))
    return Constraints(n_points, d, anchors, *dist, *joints)


def pairs(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All pairs i < j in lexicographic order, so pair (i, j) has index j + n i − (i+1)(i+2)/2."""
    i, j = torch.triu_indices(n, n, offset=1)
    return i, j


def rejection_sample(
    draw: Callable[[int], State],
    gaps: Callable[[torch.Tensor], torch.Tensor],
    n: int,
    what: str,
    max_rounds: int = 1000,
) -> State:
    """Draw batches of candidates until n have no contact (all gaps >= 0); keep the first n accepted."""
    xs, vs, have = [], [], 0
    for _ in range(max_rounds):
        cand = draw(max(n, 16))
        ok = (gaps(cand.x) >= 0).all(dim=1)
        xs.append(cand.x[ok])
        vs.append(cand.v[ok])
        have += int(ok.sum())
        if have >= n:
            return State(torch.cat(xs)[:n], torch.cat(vs)[:n])
    raise ConfigError(
        f"{what}: could not sample {n} initial states out of contact in {max_rounds} rounds "
        "(bodies too large for the box?)"
    )


def check_lengths(sec: Section, key: str, values: list, n: int) -> None:
    if len(values) != n:
        raise ConfigError(f"{sec.prefix}.{key} has {len(values)} values, expected {n}")
