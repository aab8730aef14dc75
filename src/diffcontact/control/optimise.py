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
    """Minimise ‖r(θ)‖² from θ0 (n,), or from K starts at once (θ0 (K, n)), by damped Gauss–Newton steps, at most
    ``max_simulations`` simulations; stop once the loss is <= ``tol``, or when every start has had ``patience``
    simulations in a row that lowered its loss by less than the fraction ``stall`` (a minimum of the smooth piece of
    the loss it is in) or has a zero gradient.

    The step of a start in scaled variables z = θ/scale (``scale`` (n,), the size of a meaningful change of each
    entry) is δz = −J̃ᵀ(J̃J̃ᵀ + λI)⁻¹r with J̃ = J·diag(scale) (the minimum-norm Gauss–Newton step when m < n and
    λ → 0), with λ = ``damping``·tr(J̃J̃ᵀ)/m. Each simulation tries ``trials`` lengths along it, for every start
    still moving, in one batch: min(‖δz‖, ρ)·2^−k, k < trials, ρ the start's trust radius (first ``radius``). A
    start's best candidate is kept if it lowers its loss, and ρ becomes twice its length; otherwise ρ shrinks by
    2^trials. Non-finite candidates count as no descent. The history records, per simulation, the best candidate
    of all starts.
    """
    if max_simulations < 1:
        raise ConfigError(f"max_simulations = {max_simulations} is not >= 1")
    if not radius > 0:
        raise ConfigError(f"radius = {radius!r} is not > 0")
    if trials < 1:
        raise ConfigError(f"trials = {trials} is not >= 1")
    theta = theta0.detach().clone().reshape(-1, theta0.shape[-1])  # (K, n)
    K = theta.shape[0]
    scale = torch.ones_like(theta[0]) if scale is None else scale
    hist = History()
    r, J = _start(residual, theta)  # (K, m), (K, m, n)
    loss = (r * r).sum(1)
    first = int(torch.argmin(loss))
    hist.record(theta[first], float(loss[first]), True, K)
    if progress is not None:
        progress(hist)
    halves = 2.0 ** -torch.arange(trials, dtype=theta.dtype)
    rho = torch.full((K,), float(radius), dtype=theta.dtype)
    slow = torch.zeros(K, dtype=torch.long)
    moving = torch.ones(K, dtype=torch.bool)
    eye = torch.eye(r.shape[1], dtype=r.dtype)
    while hist.simulations < max_simulations and hist.loss > tol:
        Js = J * scale
        JJ = Js @ Js.transpose(1, 2)
        trace = JJ.diagonal(dim1=1, dim2=2).sum(1)
        moving &= trace > 0
        if not moving.any():
            hist.stop = hist.stop or "the gradient is zero"
            break
        idx = moving.nonzero()[:, 0]
        lam = damping * trace[idx] / r.shape[1]
        rhs = torch.linalg.solve(JJ[idx] + lam[:, None, None] * eye, r[idx])
        dz = -(Js[idx].transpose(1, 2) @ rhs[..., None])[..., 0]  # (A, n)
        norm = dz.norm(dim=1)
        lengths = torch.minimum(norm, rho[idx])[:, None] * halves  # (A, trials)
        cands = theta[idx, None] + scale * (dz / norm[:, None])[:, None] * lengths[..., None]  # (A, trials, n)
        try:
            r2, J2 = residual_and_jacobian(residual, cands.reshape(-1, theta.shape[1]))
            losses = (r2 * r2).sum(1).reshape(len(idx), trials)
        except FloatingPointError:
            r2 = J2 = None
            losses = torch.full((len(idx), trials), float("inf"), dtype=theta.dtype)
        best = torch.argmin(losses, 1)  # (A,)
        best_loss = losses[torch.arange(len(idx)), best]
        keep = best_loss < loss[idx]
        slow[idx] = torch.where(best_loss < (1 - stall) * loss[idx], 0, slow[idx] + 1)
        top = int(torch.argmin(best_loss))
        hist.record(cands[top, best[top]], float(best_loss[top]), bool(keep[top]), len(idx) * trials)
        if r2 is not None and J2 is not None:
            pick = torch.arange(len(idx))
            rows = pick * trials + best
            theta[idx] = torch.where(keep[:, None], cands[pick, best], theta[idx])
            r[idx] = torch.where(keep[:, None], r2[rows], r[idx])
            J[idx] = torch.where(keep[:, None, None], J2[rows], J[idx])
            loss[idx] = torch.where(keep, best_loss, loss[idx])
        rho[idx] = torch.where(keep, 2 * lengths[torch.arange(len(idx)), best], lengths[:, -1] / 2)
        moving &= slow < patience
        if progress is not None:
            progress(hist)
        if not moving.any():
            what = f"{patience} simulations in a row lowered the loss by < {stall:g} of it"
            hist.stop = f"stalled: {what}" if K == 1 else f"stalled: every start had {what}"
            break
    hist.stop = hist.stop or ("tolerance reached" if hist.loss <= tol else "simulation budget used")
    return hist


def _start(residual: Residual, theta0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """r (K, m) and J (K, m, n) at the starts θ0 (K, n); InfeasibleControlError if r is not finite at one."""
    r, J = residual_and_jacobian(residual, theta0)
    bad = ~torch.isfinite(r).all(1)
    if bad.any():
        at = theta0[bad][0]
        raise InfeasibleControlError(f"the initial control θ0 = {at.tolist()} is infeasible (residual {r[bad][0]})")
    return r, J


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
