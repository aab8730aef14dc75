"""How firmly the training data fix each learned contact property, judged from the learned model alone (no truth):
the ``evidence`` of learned.json's μ and e.

For a coefficient c (one per contact slot, or one shared by all slots on a homogeneous task), its evidence is the
training chunks with a collision of its slots under the learned model (a contact of the slot active at some step
when each step is replayed from the recorded frame before it).  Around the learned θ = (μ_c, e_c) the residuals
r(θ) of those chunks (predicted − recorded positions in m and velocities in m/s, frames 1 … L − 1, every property
but θ as learned) are linearised by forward differences, J = ∂r/∂θ, and the standard errors are those of nonlinear
least squares, clustered by chunk: the square roots of the diagonal of H⁻¹ M H⁻¹ · B/(B − 1), with H = JᵀJ,
M = Σ_c g_c g_cᵀ, g_c = J_cᵀ r_c the chunk c's share of the gradient, and B chunks.  With independent residuals of
one variance σ² this is the Laplace approximation σ² H⁻¹; unlike it, it holds when a chunk's residuals are
correlated (noise on its first frame runs through all of them) or the model is not exact (real data), where σ² H⁻¹
is far too small.  A property nothing in the data moves (μ of a slot whose every contact sticks or has no tangent,
e of a slot whose restitution never binds) has J's column 0 and an infinite standard error, as has one seen in a
single chunk.  A property is ``identified`` when its standard error is at most ``tolerance / 2`` (its
95 % interval within ± tolerance).  What the standard error does not see: a model error elsewhere that the
property compensates (it is conditional on every other property as learned).

What the standard error does not see either: the bias of noisy data.  On a dataset recorded with observation noise
of standard deviation σ, every chunk starts from a noisy state (on the rope, links stretched or compressed past
their limits), which moves the least-squares μ and e without widening their spread between chunks: on the Rope at
σ = 0.05 the refined e was 0.299 with a standard error of 9e-5, where the truth is 0.  There a coefficient is also
judged by a parametric bootstrap: its chunks are simulated again from their recorded first frames with the
learned model, the recorded noise is added to every frame (``data.noise.add_noise``), and (μ, e) are fitted again
by Gauss–Newton from the learned values; ``bootstrap_error`` is the root mean square over ``DRAWS`` such data sets
of the refitted minus the learned value, which holds the estimator's bias and spread at that noise.  A property is
then identified when its standard error and its bootstrap error are both at most ``tolerance / 2``.
"""

from __future__ import annotations

import copy
import math

import torch

from diffcontact.data.noise import add_noise
from diffcontact.state import Params, State

TOLERANCE = 0.01  # (identified: a 95 % interval within ± this)
_STEP = 1e-5  # (finite-difference step of μ and e)
_SINGULAR = 1e-12  # (an eigenvalue of JᵀJ below this times its largest: a direction the data do not fix)
_HALVINGS = 8  # (a Gauss-Newton step halved at most this often: 1/256 of it, then the refinement stops)
DRAWS = 3  # (noisy data sets of the parametric bootstrap, per coefficient)
MAX_CHUNKS = 32  # (a coefficient's chunks refined or bootstrapped: a seeded subset of at most this many)


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


def _derivative(fn, value: float, high: float, at_value: torch.Tensor) -> torch.Tensor:
    """d fn / d value by a forward difference (backward at the upper bound ``high``); ``at_value`` = fn(value).
    (One rollout each, not two: on real data a rollout of the training windows takes seconds.)"""
    b = value + _STEP if value + _STEP <= high else value - _STEP
    return (fn(b) - at_value) / (b - value)


def information(sim, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float, slots: torch.Tensor) -> torch.Tensor:
    """JᵀJ (2, 2) of (μ, e) shared by the boolean mask ``slots`` (n_slots,), from chunks x, v (B, L, P, d): the
    Gauss–Newton Hessian of ½‖r‖² (see the module docstring)."""
    _, J = _jacobian(sim, params, x, v, dt, slots)
    return J.T @ J


def _jacobian(sim, params: Params, x, v, dt: float, slots: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The residuals r (n,) of chunks x, v and their Jacobian J (n, 2) in (μ, e) shared by ``slots``."""
    mu, e = float(params.mu[slots][0]), float(params.e[slots][0])
    r = _residuals(sim, params, x, v, dt)
    J = torch.stack(
        [
            _derivative(lambda m: _residuals(sim, _with(params, slots, m, e), x, v, dt), mu, math.inf, r),
            _derivative(lambda c: _residuals(sim, _with(params, slots, mu, c), x, v, dt), e, 1.0, r),
        ],
        1,
    )
    return r, J


def _pinv(JtJ: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(JᵀJ)⁺ (2, 2) over the directions the data fix, and the mask (2,) of properties with a share in one they do
    not."""
    lam, vec = torch.linalg.eigh(JtJ)
    fixed = lam > _SINGULAR * lam[-1].clamp_min(1e-300)
    return (vec[:, fixed] / lam[fixed]) @ vec[:, fixed].T, (vec[:, ~fixed].abs() > 1e-6).any(1)


def _errors(r: torch.Tensor, J: torch.Tensor, chunks: int) -> torch.Tensor:
    """(2,) the standard errors clustered by chunk from residuals r (n,) and J (n, 2) of ``chunks`` chunks (laid
    out as :func:`_residuals`: positions then velocities, each chunk by chunk); inf for a property with a share in
    a direction the data do not fix, and for both with fewer than 2 chunks."""
    H_inv, free = _pinv(J.T @ J)
    if chunks < 2:
        return torch.full((2,), math.inf, dtype=J.dtype)
    owner = torch.arange(chunks).repeat_interleave(r.numel() // (2 * chunks)).repeat(2)  # (the chunk of each entry)
    g = torch.zeros(chunks, 2, dtype=J.dtype).index_add_(0, owner, J * r[:, None])  # (B, 2) each chunk's gradient
    variance = (H_inv @ (g.T @ g) @ H_inv).diagonal() * chunks / (chunks - 1)
    return torch.where(free, math.inf, variance.clamp_min(0).sqrt())


def standard_errors(
    sim, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float, slots: torch.Tensor
) -> tuple[float, float]:
    """The standard errors of (μ, e) shared by the boolean mask ``slots`` (n_slots,) from chunks x, v (B, L, P, d)
    (see the module docstring); inf where the data do not fix it."""
    r, J = _jacobian(sim, params, x, v, dt, slots)
    se = _errors(r, J, len(x))
    return float(se[0]), float(se[1])


def bootstrap_errors(
    sim, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float, slots: torch.Tensor, noise: float, seed: int
) -> torch.Tensor:
    """(2,) the bootstrap errors of (μ, e) shared by ``slots`` on chunks x, v (B, L, P, d) recorded with observation
    noise ``noise`` (see the module docstring): the root mean square over ``DRAWS`` seeded noisy data sets,
    simulated from the chunks' first frames with ``params``, of the Gauss–Newton refit minus ``params``' value."""
    with torch.no_grad():
        px, pv, _ = sim.rollout(State(x[:, 0], v[:, 0]), params, dt, x.shape[1])
    theta = torch.stack([params.mu[slots][0], params.e[slots][0]])
    squares = torch.zeros(2, dtype=torch.float64)
    for draw in range(DRAWS):  # (a loop over data sets; each fit is batched over the chunks)
        generator = torch.Generator().manual_seed(seed * DRAWS + draw)
        nx, nv = add_noise(sim.system, px.flatten(0, 1), pv.flatten(0, 1), noise, generator)
        fitted, _ = _gauss_newton(sim, params, nx.view_as(px), nv.view_as(pv), dt, slots, iterations=10)
        squares += (torch.stack([fitted.mu[slots][0], fitted.e[slots][0]]) - theta).double().square()
    return (squares / DRAWS).sqrt()


def _subset(x: torch.Tensor, v: torch.Tensor, seed: int, size: int = MAX_CHUNKS) -> tuple[torch.Tensor, torch.Tensor]:
    """At most ``size`` of the chunks x, v (B, L, P, d), a seeded subset in their order."""
    if len(x) <= size:
        return x, v
    keep = torch.randperm(len(x), generator=torch.Generator().manual_seed(seed))[:size].sort().values
    return x[keep], v[keep]


def float64_copy(net):
    """A float64 copy of the model ``net`` (whatever the training's dtype) that shares its contact solver: the
    copy's failures are counted, and kept, with the net's own (``ContactSolver.counts``, ``failed``)."""
    solver = net.simulator.contact_model.solver
    return copy.deepcopy(net, {id(solver): solver}).double()


def evidence(
    net, chunk_x: torch.Tensor, chunk_v: torch.Tensor, tolerance: float = TOLERANCE, noise: float = 0.0
) -> dict:
    """Per contact coefficient of the model ``net`` (a ContactModelNet with LearnedParams) on its training chunks
    chunk_x, chunk_v (N, L, P, d), recorded with observation noise ``noise`` (m, m/s; 0: none recorded):
    ``{"chunks": [...], "mu": {"std_error", "bootstrap_error", "identified"}, "e": {...}}``, lists of one entry per
    coefficient (one on a homogeneous task); a standard error is None where infinite, a bootstrap error None there
    and without noise (see the module docstring)."""
    net = float64_copy(net)
    sim, learned = net.simulator, net.params
    x, v = chunk_x.detach().double(), chunk_v.detach().double()
    with torch.no_grad():
        params = learned()
    params = params.replace(mu=params.mu.detach(), e=params.e.detach())
    n_coef = 1 if learned.homogeneous else learned.n_slots
    hit = chunk_slots(sim, params, x, v, net.dt)
    keys = ("std_error", "bootstrap_error", "identified")
    out: dict = {"chunks": [], "mu": {k: [] for k in keys}, "e": {k: [] for k in keys}}
    for c in range(n_coef):  # (a loop over the parameters; each fit is one batched rollout of its chunks)
        slots = torch.ones(learned.n_slots, dtype=torch.bool) if n_coef == 1 else torch.arange(learned.n_slots) == c
        mine = hit[:, slots].any(1)
        out["chunks"].append(int(mine.sum()))
        se = standard_errors(sim, params, x[mine], v[mine], net.dt, slots) if mine.any() else (math.inf, math.inf)
        boot = (None, None)
        if noise > 0 and mine.any():
            boot = tuple(bootstrap_errors(sim, params, x[mine], v[mine], net.dt, slots, noise, c).tolist())
        for key, value, spread in zip(("mu", "e"), se, boot):
            # (3 digits: what a standard error means; the finite differences vary in the 8th with the thread count)
            out[key]["std_error"].append(float(f"{value:.3g}") if math.isfinite(value) else None)
            # (a property the data do not fix has no bootstrap either: its refits cannot move it)
            fixed = spread is not None and math.isfinite(value)
            out[key]["bootstrap_error"].append(float(f"{spread:.3g}") if fixed else None)
            out[key]["identified"].append(bool(value <= tolerance / 2 and (spread is None or spread <= tolerance / 2)))
    return out


def _coefficients(learned) -> list[torch.Tensor]:
    """The slot mask (n_slots,) of each learned coefficient: one for all slots on a homogeneous task."""
    if learned.homogeneous:
        return [torch.ones(learned.n_slots, dtype=torch.bool)]
    return [torch.arange(learned.n_slots) == c for c in range(learned.n_slots)]


def refine(
    net,
    chunk_x: torch.Tensor,
    chunk_v: torch.Tensor,
    iterations: int = 10,
    tolerance: float = TOLERANCE,
    max_chunks: int = MAX_CHUNKS,
    noise: float = 0.0,
) -> dict:
    """Gauss–Newton on each learned coefficient's (μ, e), every other property fixed, on the training chunks with a
    collision of its slots (chunk_x, chunk_v (N, L, P, d)), in place on ``net.params`` (projected transforms).

    Gradient descent leaves a coefficient short of its minimum where few contacts inform it (a weak gradient that
    the decaying learning rate stops); the squared residuals of its chunks, a function of two numbers, are
    minimised directly.  A step moves only along the directions the data fix (a pseudo-inverse), is kept in μ ≥ 0,
    e ∈ [0, 1], and is halved until the squared residuals fall (at most 8 times); a coefficient's refinement stops
    when they fall by less than a millionth.  At its end, a property that moved must be identified there (a
    standard error, and on data recorded with observation noise ``noise`` a bootstrap error, at most
    ``tolerance / 2``, as in :func:`evidence`); otherwise the coefficient goes back to its value as trained: a weakly
    fixed property would follow the noise of a few chunks.  A coefficient seen in more
    than ``max_chunks`` chunks is refined on a seeded subset of that many: a homogeneous task's one coefficient sees
    every collision, and on the real cube's windows of 80 frames all 378 took 16 minutes, 128 of them 12 (on a
    machine loaded 2 to 1).
    Returns {"mu_before", "e_before": the coefficients before (lists), "iterations": the steps kept,
    "reverted": the coefficients put back}."""
    learned = net.params
    before = {"mu_before": learned.mu_raw.detach().tolist(), "e_before": learned.e_raw.detach().tolist()}
    if learned.mu_transform != "projected" or learned.e_transform != "projected":
        return {**before, "iterations": 0, "reverted": [], "skipped": "only projected transforms hold μ, e as they are"}
    work = float64_copy(net)
    sim, x, v = work.simulator, chunk_x.detach().double(), chunk_v.detach().double()
    with torch.no_grad():
        params = work.params()
    params = params.replace(mu=params.mu.detach().clone(), e=params.e.detach().clone())
    hit = chunk_slots(sim, params, x, v, net.dt)
    steps, reverted = 0, []
    for c, slots in enumerate(_coefficients(learned)):  # (a loop over the parameters, each a batched rollout)
        mine = hit[:, slots].any(1)
        if not mine.any():
            continue
        xs, vs = x[mine], v[mine]
        xs, vs = _subset(xs, vs, c, max_chunks)  # (two numbers need no more, and a real toss's window is long)
        start = params
        fitted, taken = _gauss_newton(sim, params, xs, vs, net.dt, slots, iterations)
        if not taken:
            continue
        r, J = _jacobian(sim, fitted, xs, vs, net.dt, slots)
        moved = torch.stack([fitted.mu[slots][0] != start.mu[slots][0], fitted.e[slots][0] != start.e[slots][0]])
        spread = _errors(r, J, len(xs))
        if noise > 0 and bool(moved.any()):
            spread = torch.maximum(spread, bootstrap_errors(sim, fitted, xs, vs, net.dt, slots, noise, c))
        if bool((moved & ~(spread <= tolerance / 2)).any()):
            reverted.append(c)
            continue
        params, steps = fitted, steps + taken
        with torch.no_grad():
            learned.mu_raw[c], learned.e_raw[c] = float(fitted.mu[slots][0]), float(fitted.e[slots][0])
    return {**before, "iterations": steps, "reverted": reverted}


def _gauss_newton(sim, params: Params, x, v, dt: float, slots: torch.Tensor, iterations: int) -> tuple[Params, int]:
    """``refine``'s steps for the coefficient of ``slots`` on chunks x, v: the params after, and the steps taken."""
    taken = 0
    for _ in range(iterations):
        r, J = _jacobian(sim, params, x, v, dt, slots)
        step = _pinv(J.T @ J)[0] @ (J.T @ r)
        cost, theta = float(r.square().sum()), torch.stack([params.mu[slots][0], params.e[slots][0]])
        new_cost, trial = cost, params
        for _ in range(_HALVINGS):
            mu, e = float((theta[0] - step[0]).clamp_min(0)), float((theta[1] - step[1]).clamp(0, 1))
            trial = _with(params, slots, mu, e)
            new_cost = float(_residuals(sim, trial, x, v, dt).square().sum())
            if new_cost < cost:
                break
            step = step / 2
        else:
            break  # (no step lowers the residuals: at the minimum, to rounding)
        params, taken = trial, taken + 1
        if float(step.abs().max()) < 1e-9 or new_cost > (1 - 1e-6) * cost:
            break  # (converged: the step or the fall of the residuals is below rounding's scale)
    return params, taken
