"""Test rollouts: the ground truth of a split and a model's prediction from the same initial states."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from diffcontact.data.store import load_meta, load_split
from diffcontact.errors import DatasetError


@dataclass(frozen=True)
class Rollouts:
    """Truth and prediction over ``frames`` frames from the split's initial states, float64, (N, T, P, d) in m and
    m/s; ``contact`` (N, T) marks the true frames at which an impulse was applied."""

    x: torch.Tensor
    v: torch.Tensor
    contact: torch.Tensor
    x_hat: torch.Tensor
    v_hat: torch.Tensor
    dt: float


def ground_truth(folder: str | Path, split: str = "test", frames: int | None = None, config=None):
    """The split's trajectories, which the dataset records as simulated with the exact contact model (CM) in float64
    from their initial states (the ground truth for every model, whatever its own contact model); x, v (N, T, P, d),
    contact (N, T), dt.  DatasetError if the data were made otherwise, from another config than ``config`` (a
    TaskConfig; default: the packaged task of the dataset's name) or are shorter than ``frames``."""
    request = load_meta(folder)["request"]
    made = {k: request.get(k) for k in ("contact_model", "dtype", "dynamics")}
    if made != {"contact_model": "CM", "dtype": "float64", "dynamics": "lagrangian"}:
        raise DatasetError(f"{folder}: the ground truth must be CM in float64 (Lagrangian), the data record {made}")
    data = load_split(folder, split, config)
    T = data.x.shape[1]
    frames = T if frames is None else frames
    if not 2 <= frames <= T:
        raise DatasetError(f"frames = {frames} is not in [2, {T}] (the frames of {folder}/{split})")
    return data.x[:, :frames], data.v[:, :frames], data.contact[:, :frames], data.dt


def predict(net: nn.Module, x0: torch.Tensor, v0: torch.Tensor, frames: int, batch: int = 100):
    """A model's rollout in float64 from x0, v0 (N, P, d): xs, vs (N, frames, P, d), ``batch`` trajectories at once.

    A model that diverges (FloatingPointError: a non-finite state) is rolled out again one trajectory at a time,
    and a diverging trajectory keeps its frames up to the last finite one; the frames after it are NaN."""
    net = net.to(torch.float64)
    xs, vs = [], []
    with torch.no_grad():
        for i in range(0, x0.shape[0], batch):
            xb, vb = x0[i : i + batch].double(), v0[i : i + batch].double()
            try:
                x, v = net(xb, vb, frames)
            except FloatingPointError:
                x, v = (torch.cat(t) for t in zip(*(_finite_prefix(net, xb[j : j + 1], vb[j : j + 1], frames)
                                                     for j in range(len(xb)))))  # fmt: skip
            xs.append(x.detach())
            vs.append(v.detach())
    return torch.cat(xs), torch.cat(vs)


def _finite_prefix(net: nn.Module, x0: torch.Tensor, v0: torch.Tensor, frames: int):
    """One trajectory's rollout (1, frames, P, d), NaN from the first frame the model cannot reach finitely (the
    longest finite rollout, found by bisection on the number of frames)."""
    try:
        return net(x0, v0, frames)
    except FloatingPointError:
        pass
    good, bad = 1, frames  # (frame 0 is the given state)
    while bad - good > 1:
        mid = (good + bad) // 2
        try:
            net(x0, v0, mid)
            good = mid
        except FloatingPointError:
            bad = mid
    x, v = net(x0, v0, good)
    pad = torch.full((1, frames - good, *x.shape[2:]), float("nan"), dtype=x.dtype)
    return torch.cat([x, pad], 1), torch.cat([v, pad], 1)


def rollout_split(
    net: nn.Module, folder: str | Path, split: str = "test", frames: int | None = None, config=None
) -> Rollouts:
    """Ground truth (``ground_truth``) and the model's prediction from the same initial states."""
    x, v, contact, dt = ground_truth(folder, split, frames, config)
    x_hat, v_hat = predict(net, x[:, 0], v[:, 0], x.shape[1])
    if x_hat.shape != x.shape:
        raise ValueError(f"the model predicted {tuple(x_hat.shape)}, the truth is {tuple(x.shape)} (N, T, P, d)")
    return Rollouts(x=x, v=v, contact=contact, x_hat=x_hat, v_hat=v_hat, dt=dt)
