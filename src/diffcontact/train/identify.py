"""How firmly the training data fix each learned contact property, judged from the learned model alone (no truth):
the ``evidence`` of learned.json's μ and e.

For a coefficient c (one per contact slot, or one shared by all slots on a homogeneous task), its evidence is the
training chunks with a collision of its slots under the learned model (a contact of the slot active at some step
when each step is replayed from the recorded frame before it).  Around the learned θ = (μ_c, e_c) the residuals
r(θ) of those chunks (predicted − recorded positions in m and velocities in m/s, frames 1 … L − 1, every property
but θ as learned) are linearised by finite differences, J = ∂r/∂θ, and the standard errors are those of nonlinear
least squares (the Laplace approximation of a Gaussian likelihood): the square roots of the diagonal of
σ² (JᵀJ)⁻¹, with σ² = ‖r‖² / (n − 2) the residuals' variance.  A property nothing in the data moves (μ of a slot
whose every contact sticks or has no tangent, e of a slot whose restitution never binds) has J's column 0 and an
infinite standard error.  A property is ``identified`` when its standard error is at most ``tolerance / 2`` (its
95 % interval within ± tolerance).  What the standard error does not see: a model error elsewhere that the
property compensates (it is conditional on every other property as learned).
"""

from __future__ import annotations

import copy
import math

import torch

from diffcontact.state import Params, State

TOLERANCE = 0.01  # (identified: a 95 % interval within ± this)
_STEP = 1e-5  # (finite-difference step of μ and e)
_SINGULAR = 1e-12  # (an eigenvalue of JᵀJ below this times its largest: a direction the data do not fix)


def chunk_slots(sim, params: Params, chunk_x: torch.Tensor, chunk_v: torch.Tensor, dt: float) -> torch.Tensor:
    """(N, n_slots) bool: the chunks x, v (N, L, P, d) with a collision of each slot under ``params``, each step
    replayed from the recorded frame before it (one batched step per frame)."""
    N, L = chunk_x.shape[:2]
    hit = torch.zeros(N, params.mu.numel(), dtype=torch.bool)
    det = sim.system.detector
    if not det.kinds:
        return hit
    x0, v0 = (c[:, :-1].flatten(0, 1) for c in (chunk_x, chunk_v))
    with torch.no_grad():
        x1, _ = sim.flow(params, x0, v0, dt)
        contacts = det.detect(x1)
    if contacts is None:
        return hit
    rows = contacts.index[:, None].expand_as(contacts.slot)[contacts.active] // (L - 1)  # (the chunk of each step)
    hit[rows, contacts.slot[contacts.active]] = True
    return hit


def _residuals(sim, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float) -> torch.Tensor:
    """(n,) the residuals of chunks x, v (B, L, P, d): predicted − recorded positions and velocities, frames 1 on."""
    with torch.no_grad():
        px, pv, _ = sim.rollout(State(x[:, 0], v[:, 0]), params, dt, x.shape[1])
    return torch.cat([(px - x)[:, 1:].flatten(), (pv - v)[:, 1:].flatten()])


def _with(params: Params, slots: torch.Tensor, mu: float, e: float) -> Params:
    return params.replace(mu=torch.where(slots, mu, params.mu), e=torch.where(slots, e, params.e))


def _derivative(fn, value: float, low: float, high: float) -> torch.Tensor:
    """d fn / d value by central differences, one-sided at a bound of [low, high]."""
    a, b = max(value - _STEP, low), min(value + _STEP, high)
    return (fn(b) - fn(a)) / (b - a)


def information(
    sim, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float, slots: torch.Tensor
) -> tuple[torch.Tensor, float]:
    """JᵀJ (2, 2) of (μ, e) shared by the boolean mask ``slots`` (n_slots,), and the residuals' variance σ², from
    chunks x, v (B, L, P, d) (see the module docstring)."""
    mu, e = float(params.mu[slots][0]), float(params.e[slots][0])
    r = _residuals(sim, params, x, v, dt)
    J = torch.stack(
        [
            _derivative(lambda m: _residuals(sim, _with(params, slots, m, e), x, v, dt), mu, 0.0, math.inf),
            _derivative(lambda c: _residuals(sim, _with(params, slots, mu, c), x, v, dt), e, 0.0, 1.0),
        ],
        1,
    )  # (n, 2)
    return J.T @ J, float(r.square().sum()) / max(r.numel() - 2, 1)


def standard_errors(
    sim, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float, slots: torch.Tensor
) -> tuple[float, float]:
    """The standard errors of (μ, e) shared by the boolean mask ``slots`` (n_slots,) from chunks x, v (B, L, P, d)
    (see the module docstring); inf where the data do not fix it."""
    JtJ, sigma2 = information(sim, params, x, v, dt, slots)
    lam, vec = torch.linalg.eigh(JtJ)
    fixed = lam > _SINGULAR * lam[-1].clamp_min(1e-300)
    variance = (vec[:, fixed].square() / lam[fixed]).sum(1) * sigma2  # (the pseudo-inverse's diagonal)
    free = (vec[:, ~fixed].abs() > 1e-6).any(1)  # (a property with a share in an unfixed direction)
    se = torch.where(free, math.inf, variance.sqrt())
    return float(se[0]), float(se[1])


def evidence(net, chunk_x: torch.Tensor, chunk_v: torch.Tensor, tolerance: float = TOLERANCE) -> dict:
    """Per contact coefficient of the model ``net`` (a ContactModelNet with LearnedParams) on its training chunks
    chunk_x, chunk_v (N, L, P, d): ``{"chunks": [...], "mu": {"std_error", "identified"}, "e": {...}}``, lists of
    one entry per coefficient (one on a homogeneous task); a standard error is None where infinite."""
    net = copy.deepcopy(net).double()  # (float64, whatever the training's dtype)
    sim, learned = net.simulator, net.params
    x, v = chunk_x.detach().double(), chunk_v.detach().double()
    with torch.no_grad():
        params = learned()
    params = params.replace(mu=params.mu.detach(), e=params.e.detach())
    n_coef = 1 if learned.homogeneous else learned.n_slots
    hit = chunk_slots(sim, params, x, v, net.dt)
    out: dict = {"chunks": [], "mu": {"std_error": [], "identified": []}, "e": {"std_error": [], "identified": []}}
    for c in range(n_coef):  # (a loop over the parameters; each fit is one batched rollout of its chunks)
        slots = torch.ones(learned.n_slots, dtype=torch.bool) if n_coef == 1 else torch.arange(learned.n_slots) == c
        mine = hit[:, slots].any(1)
        out["chunks"].append(int(mine.sum()))
        se = standard_errors(sim, params, x[mine], v[mine], net.dt, slots) if mine.any() else (math.inf, math.inf)
        for key, value in zip(("mu", "e"), se):
            # (3 digits: what a standard error means; the finite differences vary in the 8th with the thread count)
            out[key]["std_error"].append(float(f"{value:.3g}") if math.isfinite(value) else None)
            out[key]["identified"].append(bool(value <= tolerance / 2))
    return out
