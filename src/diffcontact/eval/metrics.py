"""Trajectory metrics as published (paper Sec. 5): relative error per frame, the 5-step error with its 95 % interval
(paper Fig. 3), the error curve (Fig. 4) and the true energy along a trajectory (Fig. 5).

Every function takes the ground truth (the exact contact model CM in float64, from the same initial states) and
the prediction as tensors batch first: x, v (N trajectories, T frames, P points, d dims) in m and m/s.
"""

from __future__ import annotations

import math

import torch


def relative_error(
    x_hat: torch.Tensor, v_hat: torch.Tensor, x: torch.Tensor, v: torch.Tensor, diverged_ok: bool = False
) -> torch.Tensor:
    """‖ẑ_t − z_t‖ / ‖z_t‖ per trajectory and frame, the norms over every position and velocity entry of the frame
    (z = (x, v)): x_hat, v_hat, x, v (N, T, P, d) -> (N, T), dimensionless.

    A non-finite predicted frame raises FloatingPointError, or with ``diverged_ok`` (a model that diverged) has
    the error +inf; ValueError for a true frame that is all zeros.
    """
    if x_hat.shape != x.shape or v_hat.shape != v.shape or x.shape != v.shape:
        raise ValueError(f"shapes differ: x_hat {tuple(x_hat.shape)}, v_hat {tuple(v_hat.shape)}, x {tuple(x.shape)}")
    bad = ~(torch.isfinite(x_hat) & torch.isfinite(v_hat)).flatten(2).all(-1)  # (N, T)
    if bad.any() and not diverged_ok:
        n, t = (int(i) for i in bad.nonzero()[0])
        raise FloatingPointError(f"the prediction is not finite from trajectory {n}, frame {t}")
    num = (x_hat - x).square().flatten(2).sum(-1) + (v_hat - v).square().flatten(2).sum(-1)
    den = x.square().flatten(2).sum(-1) + v.square().flatten(2).sum(-1)
    if (den == 0).any():
        n, t = (int(i) for i in (den == 0).nonzero()[0])
        raise ValueError(f"true state of trajectory {n} at frame {t} is zero: the relative error is undefined")
    return (num / den).sqrt().masked_fill(bad, float("inf"))


def trajectory_error(rel: torch.Tensor, steps: int = 5) -> torch.Tensor:
    """The Fig. 3 error of each trajectory: the relative error summed over frames 0 … steps − 1 (frame 0 is the
    initial state): rel (N, T) -> (N,)."""
    if not 1 <= steps <= rel.shape[1]:
        raise ValueError(f"steps = {steps} is not in [1, {rel.shape[1]}] (the frames given)")
    return rel[:, :steps].sum(1)


def mean_interval(values: torch.Tensor, level: float = 0.95) -> tuple[float, float | None]:
    """Mean of ``values`` (N,) and the half width of its ``level`` confidence interval, sem · t_{(1+level)/2, N−1}
    (Student's t; the published error bars). The half width is None for N < 2."""
    from scipy.stats import t as student_t

    n = values.numel()
    if n == 0:
        raise ValueError("no values: the mean is undefined")
    mean = float(values.double().mean())
    if n < 2:
        return mean, None
    sem = float(values.double().std(unbiased=True)) / math.sqrt(n)
    return mean, sem * float(student_t.ppf(0.5 + level / 2, n - 1))


def error_curve(rel: torch.Tensor, frames: int = 50) -> torch.Tensor:
    """Fig. 4: the relative error of frames t = 0 … frames − 1, averaged over the trajectories: (N, T) -> (frames,)."""
    if not 1 <= frames <= rel.shape[1]:
        raise ValueError(f"frames = {frames} is not in [1, {rel.shape[1]}] (the frames given)")
    return rel[:, :frames].mean(0)


def true_energy(task, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The true total energy ½vᵀMv + V(x) and the true kinetic energy ½vᵀMv of the task's true parameters along
    trajectories: x, v (N, T, P, d) -> ((N, T), (N, T)) in J (float64)."""
    N, T = x.shape[:2]
    x64, v64 = (a.to(torch.float64).flatten(0, 1) for a in (x, v))
    with torch.no_grad():
        total = task.system.energy(task.params, x64, v64).reshape(N, T)
        potential = task.system.energy(task.params, x64, torch.zeros_like(v64)).reshape(N, T)
    return total, total - potential


def energy_deviation(energy_hat: torch.Tensor, energy: torch.Tensor, kinetic: torch.Tensor) -> torch.Tensor:
    """|E(ẑ_t) − E(z_t)| relative to the energy in motion of each true trajectory, its largest kinetic energy over
    the frames given (for a conservative system E(z_0) − min_t V(x_t); unlike |E(z_0)| it does not depend on where
    the potential's zero lies, which makes a pendulum's E(z_0) near 0 J for some starts): energy_hat, energy,
    kinetic (N, T) in J -> (N, T). ValueError for a trajectory that never moves."""
    scale = kinetic.amax(1, keepdim=True)
    if (scale <= 0).any():
        raise ValueError(f"true trajectory {int((scale[:, 0] <= 0).nonzero()[0])} never moves (kinetic energy 0 J)")
    return (energy_hat - energy).abs() / scale
