"""Optimisers of a control variable θ through the simulator: Levenberg–Marquardt (damped Gauss–Newton) on a
residual, with a batched line search, and Adam on its squared norm.

A problem gives a batched ``residual(θ) -> r``: θ (B, n) float64 (B candidate controls), r (B, m) differentiable
(autograd through the Simulator, which simulates the B candidates in one batch); the loss is ‖r‖². A row of r is
inf where its θ is outside the problem's domain (bodies overlapping at the start, an event that never happens).
The cost unit is the *simulation*: one batched rollout with its gradient (the published downstream tasks run one
simulation of one candidate per iteration).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from diffcontact.errors import ConfigError, DiffContactError

Residual = Callable[[torch.Tensor], torch.Tensor]
"""θ (B, n) -> r (B, m): the residual whose squared norm is the loss (rows of inf where θ is infeasible)."""

OPTIMISERS = ("lm", "adam")


class InfeasibleControlError(DiffContactError, ValueError):
    """The initial control θ0 is outside its problem's domain (its residual is not finite)."""


@dataclass
class History:
    """One row per simulation: the loss ‖r‖² of its best candidate, that candidate θ, and whether the optimiser
    moved there (LM keeps a step only if it lowers the loss). ``theta``: the best θ found, ``loss`` its loss;
    ``trajectories``: candidates simulated in all."""

    losses: list[float] = field(default_factory=list)
    thetas: list[list[float]] = field(default_factory=list)
    accepted: list[bool] = field(default_factory=list)
    theta: torch.Tensor | None = None
    loss: float = float("inf")
    trajectories: int = 0
    stop: str = ""

    @property
    def simulations(self) -> int:
        return len(self.losses)

    def record(self, theta: torch.Tensor, loss: float, accepted: bool, candidates: int = 1) -> None:
        self.losses.append(loss)
        self.thetas.append(theta.detach().tolist())
        self.accepted.append(accepted)
        self.trajectories += candidates
        if accepted and loss < self.loss:
            self.theta, self.loss = theta.detach().clone(), loss


def residual_and_jacobian(residual: Residual, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """r (B, m) and its Jacobians J (B, m, n) at θ (B, n): one batched simulation, m backward passes (rows of
    different candidates are independent, so the gradient of a column's sum gives every candidate's row)."""
    th = theta.detach().clone().requires_grad_(True)
    r = residual(th)
    if torch.isnan(r).any():
        raise FloatingPointError(f"the residual is NaN at θ = {th.detach().tolist()}")
    m = r.shape[1]
    cols = [torch.autograd.grad(r[:, i].sum(), th, retain_graph=i + 1 < m, allow_unused=True)[0] for i in range(m)]
    cols = [torch.zeros_like(th) if c is None else c for c in cols]
    return r.detach(), torch.stack(cols, 1)


def levenberg_marquardt(
    residual: Residual,
    theta0: torch.Tensor,
    max_simulations: int,
    tol: float = 0.0,
    scale: torch.Tensor | None = None,
    radius: float = 1.0,
    trials: int = 1,
    damping: float = 1e-6,
    stall: float = 1e-4,
    patience: int = 3,
    progress: Callable[[History], None] | None = None,
) -> History:
    """Minimise ‖r(θ)‖² from θ0 (n,) by damped Gauss–Newton steps, at most ``max_simulations`` simulations; stop
    once the loss is <= ``tol``, or when ``patience`` simulations in a row lowered it by less than the fraction
    ``stall`` (a minimum of the smooth piece of the loss the search is in).

    The step in scaled variables z = θ/scale (``scale`` (n,), the size of a meaningful change of each entry) is
    δz = −J̃ᵀ(J̃J̃ᵀ + λI)⁻¹r with J̃ = J·diag(scale) (the minimum-norm Gauss–Newton step when m < n and λ → 0), with
    λ = ``damping``·tr(J̃J̃ᵀ)/m. Each simulation tries ``trials`` lengths along it in one batch: min(‖δz‖, ρ)·2^−k,
    k < trials, ρ the trust radius (first ``radius``). The best candidate is kept if it lowers the loss, and ρ
    becomes twice its length; otherwise ρ shrinks by 2^trials. Non-finite candidates count as no descent.
    """
    if max_simulations < 1:
        raise ConfigError(f"max_simulations = {max_simulations} is not >= 1")
    if not radius > 0:
        raise ConfigError(f"radius = {radius!r} is not > 0")
    if trials < 1:
        raise ConfigError(f"trials = {trials} is not >= 1")
    scale = torch.ones_like(theta0) if scale is None else scale
    hist = History()
    theta = theta0.detach().clone()
    r, J = _start(residual, theta)
    hist.record(theta, float(r @ r), True)
    if progress is not None:
        progress(hist)
    halves = 2.0 ** -torch.arange(trials, dtype=theta.dtype)
    slow = 0
    while hist.simulations < max_simulations and hist.loss > tol:
        Js = J * scale
        JJ = Js @ Js.T
        if not float(JJ.trace()) > 0:
            hist.stop = "the gradient is zero"
            break
        lam = damping * float(JJ.trace()) / J.shape[0]
        dz = -Js.T @ torch.linalg.solve(JJ + lam * torch.eye(J.shape[0], dtype=J.dtype), r)
        lengths = min(float(dz.norm()), radius) * halves
        cands = theta + scale * (dz / dz.norm()) * lengths[:, None]
        try:
            r2, J2 = residual_and_jacobian(residual, cands)
            losses = (r2 * r2).sum(1)
        except FloatingPointError:
            losses = torch.full((trials,), float("inf"), dtype=theta.dtype)
        best = int(torch.argmin(losses))
        keep = bool(losses[best] < hist.loss)
        slow = 0 if float(losses[best]) < (1 - stall) * hist.loss else slow + 1
        hist.record(cands[best], float(losses[best]), keep, trials)
        if keep:
            theta, r, J, radius = cands[best], r2[best], J2[best], 2 * float(lengths[best])
        else:
            radius = float(lengths[-1]) / 2
        if progress is not None:
            progress(hist)
        if slow >= patience:
            hist.stop = f"stalled: {patience} simulations in a row lowered the loss by < {stall:g} of it"
            break
    hist.stop = hist.stop or ("tolerance reached" if hist.loss <= tol else "simulation budget used")
    return hist


def _start(residual: Residual, theta0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """r (m,) and J (m, n) at θ0 (n,); InfeasibleControlError if r is not finite there."""
    r, J = residual_and_jacobian(residual, theta0[None])
    if not torch.isfinite(r).all():
        raise InfeasibleControlError(f"the initial control θ0 = {theta0.tolist()} is infeasible (residual {r[0]})")
    return r[0], J[0]


def adam(
    residual: Residual,
    theta0: torch.Tensor,
    max_simulations: int,
    lr: float,
    tol: float = 0.0,
    scale: torch.Tensor | None = None,
    progress: Callable[[History], None] | None = None,
) -> History:
    """Minimise ‖r(θ)‖² from θ0 (n,) with Adam (learning rate ``lr`` in the scaled variables θ/scale), one
    simulation of one candidate per iteration, at most ``max_simulations``; stop once the loss is <= ``tol``."""
    if max_simulations < 1:
        raise ConfigError(f"max_simulations = {max_simulations} is not >= 1")
    if not lr > 0:
        raise ConfigError(f"lr = {lr!r} is not > 0")
    scale = torch.ones_like(theta0) if scale is None else scale
    z = (theta0.detach() / scale).clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr)
    hist = History()
    while hist.simulations < max_simulations:
        opt.zero_grad()
        theta = z * scale
        r = residual(theta[None])[0]
        loss = (r * r).sum()
        if not torch.isfinite(loss):
            if not hist.simulations:
                raise InfeasibleControlError(f"the initial control θ0 = {theta0.tolist()} is infeasible")
            hist.stop = f"infeasible or non-finite loss at θ = {theta.detach().tolist()}"
            break
        hist.record(theta, float(loss.detach()), True)
        if progress is not None:
            progress(hist)
        if hist.loss <= tol:
            break
        loss.backward()
        opt.step()
    hist.stop = hist.stop or ("tolerance reached" if hist.loss <= tol else "simulation budget used")
    return hist
