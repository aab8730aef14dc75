"""Flat directions of the contact QP: an A that is PSD up to rounding, and minimisers that are not unique.

The effective inverse mass A = J M⁻¹ Jᵀ (with joints: J P M⁻¹ Jᵀ) is singular whenever an impulse at the contacts
can be absorbed by the joints (a gyroscope's rim contact along the line to its pivot: A is 3×3 of rank 2); computed
in float32 its zero eigenvalues come out as ±1e-7‖A‖.  Then the QP  min ½fᵀAf + qᵀf  over the friction cones
either has a whole set of minimisers (segment or face along the null directions, all with the same velocity change
A f), or, with the rounding, no bounded one at all.  This module states what the solver does there.

Definitions (per batch element, on the rows in use: active contacts, without the tangential rows of μ = 0):

- ``ref`` = the largest diagonal entry of A on those rows (λ_max(A) ≤ n·ref).
- A direction is *flat* if it is an eigenvector v of A with eigenvalue |λ| ≤ τ·s_v, τ = ``psd_tol(dtype)`` = max(1e-6,
  100·eps(dtype)) for the input dtype (or the caller's ``flat_tol``: ``solve_cone_qp``), s_v = (Σ_i |v_i| √A_ii)²
  clipped to [``ROW_FLOOR``·ref, ref]: the scale of the rows v lives on, since a product Z Zᵀ rounds its entries
  relative to their rows (on an A whose rows are of one scale, s_v ≈ ref; on a badly row-scaled one, such as the
  limits of a long rope with rows 1e5 times apart, a real eigenvalue far below τ·ref is not taken for rounding).  A is
  *PSD up to rounding* if every eigenvalue is ≥ −τ·ref; an eigenvalue below that makes A genuinely indefinite, an
  input error (``IndefiniteMatrixError``).
- q's component along the flat directions, Π_N q, is a velocity that no contact impulse can change (the joints
  fix it): for physical data q = J v, and Π_N q = 0 when v obeys the joints (J_E v = 0).  The integrator leaves a
  drift (measured in the ground-truth simulation of the gyroscope with μ = 1.2: ‖Π_N q‖/‖q‖ median 1e-4, at most
  2e-2; in training up to 0.1 for all but 0.1 % of the problems, investigations/flat_stats.py).  It is dropped with
  the flat eigenvalues where it is at the level of A's rounding (≤ τ·‖q‖), and where it is drift
  (≤ ``Q_TOL`` = 0.1) and a flat direction enters the friction cones (where, kept, it would make the QP unbounded
  or pick the far end of an unbounded set); elsewhere the drift picks the minimiser, which is then unique, as it
  does in the published code.  Where dropped, the minimisers form a set f + (flat directions) ∩ cones with one
  velocity change A·f and one objective; the solver returns the one of **minimum norm** (so that the impulse, and
  the restitution bound e·f_n built on it, are bounded and do not depend on the solver): in closed form where
  there is one flat direction (the gyroscope; a pendulum bob); where there are several, as the projection of 0
  onto the set, by the augmented Lagrangian method on the range part with our own cone QP as the inner solver
  (``minimum_norm``; measured against Clarabel in the tests, to its accuracy).  Dropping a drift δ changes the
  solution by O(δ) where the QP is bounded, and removes the unboundedness that a drift into the cone would cause.
- Where it is kept (and for a larger flat part, a velocity that violates the joints, not drift), only the negative
  flat eigenvalues are set to zero and the problem is solved as it is: bounded if q pushes the impulse out of
  the cones along the flat directions, else reported ``UNBOUNDED`` (physically: an impulse of any size inside the
  friction cones that the joints absorb, lowering the objective without limit; the contact cannot act on that
  velocity).

Gradients are those of this map (A, q, μ, lower) → minimiser: the flat projector Π_N moves with A (first-order
eigenvector perturbation), which carries the derivative of removing q's flat part; the eigenvalues set to zero carry
none (rounding); the set of minimisers' least-norm end carries the derivative of the cone that bounds it.  Where the
minimisers are not unique, the implicit gradient is taken at a minimiser inside their set, from the problem with
curvature on the flat directions centred there (``centre_on``), which is well posed.

Most problems have no flat direction; a cheap Cholesky test (``flat_elements``) finds the ones that do, and only
those are decomposed.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from diffcontact.errors import IndefiniteMatrixError
from diffcontact.solver import kernel
from diffcontact.solver.policy import POLICY
from diffcontact.solver.status import Status, is_failure

# (thresholds and their reasons: ``solver/policy.py``)
Q_TOL, UNIQUE_TOL = POLICY.q_tol, POLICY.unique_tol
# the augmented Lagrangian stage (several flat directions): penalty relative to the unit Hessian, steps, tolerance
RHO, RHO_MAX = POLICY.alm_rho, POLICY.alm_rho_max
ALM_STEPS, ALM_TOL, ALM_ACCEPT = POLICY.alm_steps, POLICY.alm_tol, POLICY.alm_accept
# an iterate that stalls ALM_FAR times farther from its start than its relative miss is not at a point (there the
# iterates creep towards the start: 6–200 times their miss in the solver's accuracy tests); it steps on until its
# miss is below ALM_FLOOR (the inner solves' accuracy at RHO_MAX: measured up to 2e-7), then a proximal step
# (PROX, below) makes it a minimiser
ALM_FLOOR, ALM_FAR = POLICY.alm_floor, POLICY.alm_far
# parts of a unit flat direction up to this are the eigensolver's rounding (≈ eps·ref / gap ≤ eps / τ ≈ 2e-10 where
# A's rows are of one scale, its eigenvalues that are not flat then above τ·ref; on a badly row-scaled A the gap can
# be smaller, and a larger part is kept)
V_ROUNDING = POLICY.v_rounding
# an eigenvector's row scale is trusted down to this × ref (its flat threshold then τ·ROW_FLOOR·ref at the least)
ROW_FLOOR = POLICY.row_floor
# the proximal step that finishes a stalled least-norm stage: curvature relative to ref (its pull adds ≈ PROX times
# the iterate's miss to the residual)
PROX = POLICY.prox


@functools.cache
def psd_tol(dtype: torch.dtype) -> float:
    """τ of the module docstring for an input of this dtype."""
    return max(1e-6, 100.0 * torch.finfo(dtype).eps)


def rows_in_use(mu: torch.Tensor, active: torch.Tensor, d: int) -> torch.Tensor:
    """(B, K·d) bool: rows of active contacts, without the tangential rows of μ = 0 contacts."""
    used = active.repeat_interleave(d, -1)
    if d > 1:
        tangential = torch.ones(d, dtype=torch.bool, device=mu.device)
        tangential[0] = False
        used = used & ~((mu == 0).repeat_interleave(d, -1) & tangential.repeat(mu.shape[-1]))
    return used


def flat_elements(
    A: np.ndarray, mu: np.ndarray, active: np.ndarray, d: int, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B,) bool: elements whose A, on its rows in use (``rows_in_use``), has an eigenvalue ≤ tol·ref (module
    docstring); read in the same pass, (B,) bool: elements whose A is finite everywhere (the input check) and (B,)
    bool: elements whose A equals its transpose exactly (``scaling.scale_batch``).

    A: (B, n, n) float64, symmetrised on the fly (½(A + Aᵀ)); mu: (B, K) float64; active: (B, K) bool.  A Cholesky
    factorisation of A − tol·ref·I per element (its rounding error, ~n·eps·ref, is far below tol·ref), in the
    compiled kernel (``kernel.flat_test``: the rows not in use replaced by the identity, W elements at a time).
    """
    return kernel.flat_test(A, mu, active, d, tol)


def _analyse(A, q, used, tol: float, mu=None):
    """Eigen-analysis of the selected elements (float64, no autograd); see ``FlatProjection``.  mu: (B, K), to
    tell where a single flat direction enters the cones (None: assume it does)."""
    mask = used[:, :, None] & used[:, None, :]
    diag = torch.where(used, A.diagonal(dim1=-2, dim2=-1), torch.zeros_like(q))
    ref = diag.amax(-1).clamp_min(torch.finfo(A.dtype).tiny)
    # rows not in use: decoupled, with an eigenvalue (ref) that is not flat
    As = torch.where(mask, A, torch.zeros_like(A)) + torch.diag_embed((~used) * ref[:, None])
    evals, V = torch.linalg.eigh(As)
    indefinite = evals[:, 0] < -tol * ref
    # (B, n), per eigenvector: small against A's largest diagonal entry, and against the rows it lives on.  A
    # product Z Zᵀ rounds its entries relative to their rows, so an eigenvector v on rows whose diagonal is far
    # below the largest (a badly row-scaled A: the limits of a long rope, rows 1e5 times apart) has the scale
    # (Σ |v_i| √A_ii)², not max(diag A); down to ROW_FLOOR·max(diag A), below which A's absolute rounding (of an A
    # formed as J M⁻¹ Jᵀ, or of a row that is rounding itself: a contact no velocity can move) may rule
    row_scale = ((V.abs() * used[:, :, None]).mT @ diag.clamp_min(0).sqrt()[..., None])[..., 0] ** 2
    null = evals.abs() <= tol * torch.minimum(ref[:, None], torch.maximum(row_scale, ROW_FLOOR * ref[:, None]))
    qs = q * used
    VN = V * null[:, None, :] * used[:, :, None]  # (exactly 0 on rows not in use, where eigh leaves rounding)
    qN = VN.mT @ qs[..., None]
    part = qN[..., 0].norm(dim=-1) / qs.norm(dim=-1).clamp_min(torch.finfo(q.dtype).tiny)
    enters = _enters_cones(VN, null, used, mu)
    consistent = (part <= tol) | ((part <= Q_TOL) & enters)
    # q with a flat part beyond drift (Q_TOL): A is only made PSD (its negative flat eigenvalues set to 0), the
    # problem is left as it is otherwise (bounded or unbounded along those directions)
    null = null & (consistent[:, None] | (evals < 0))
    VN = V * null[:, None, :] * used[:, :, None]
    PiN = VN @ VN.mT
    N = (VN * evals[:, None, :]) @ VN.mT  # the flat part of A, removed
    return dict(
        evals=evals,
        V=V,
        null=null,
        PiN=PiN,
        N=N,
        ref=ref,
        consistent=consistent,
        indefinite=indefinite,
        part=part,
        enters=enters,
    )


def _enters_cones(VN, null, used, mu):
    """(B,) bool: the flat directions can enter the friction cones: with one flat direction v, v or −v lies in
    every active contact's cone (v_n ≥ 0, ‖v_t‖ ≤ μ v_n, up to 1e-9); with several, assumed."""
    B, n = null.shape
    enters = torch.ones(B, dtype=torch.bool, device=null.device)
    one = null.sum(-1) == 1
    if mu is None or not one.any():
        return enters
    K = mu.shape[-1]
    d = n // K
    v = VN.sum(-1).view(B, K, d)  # (the single flat eigenvector where there is one)
    rows = used.view(B, K, d)[..., 0]

    def inside(v):
        ok = v[..., 0] >= -1e-9
        if d > 1:
            ok = ok & (v[..., 1:].norm(dim=-1) <= mu * v[..., 0] + 1e-9)
        return (ok | ~rows).all(-1)

    return torch.where(one, inside(v) | inside(-v), enters)


class FlatProjection(torch.autograd.Function):
    """(A, q) → (Ã, q̃, Π_N, consistent, ref) of the selected elements (module docstring): flat eigenvalues set to
    zero and q's flat part removed where it is drift (≤ Q_TOL·‖q‖: ``consistent``); elsewhere only negative flat
    eigenvalues set to zero.  Π_N: the projector onto the directions whose eigenvalue was set to zero.

    A: (B, n, n) symmetric, q: (B, n), float64; used: (B, n) bool.  Rows not in use pass through unchanged.
    """

    @staticmethod
    def forward(ctx, A, q, used, tol, batch_index, mu=None):  # noqa: D102
        a = _analyse(A, q, used, tol, mu)
        if a["indefinite"].any():
            bad = batch_index[a["indefinite"]].tolist()
            worst = (a["evals"][:, 0] / a["ref"])[a["indefinite"]].min().item()
            raise IndefiniteMatrixError(
                f"A is not positive semidefinite in batch elements {bad[:10]}: smallest eigenvalue "
                f"{worst:.3g}·max(diag A), below the rounding tolerance −{tol:.1g} (A must be symmetric PSD)"
            )
        k = a["consistent"].to(A.dtype)[:, None]
        PiN, mask = a["PiN"], used[:, :, None] & used[:, None, :]
        At = A - torch.where(mask, a["N"], torch.zeros_like(A))
        qt = q - k * (PiN @ (q * used)[..., None])[..., 0]
        # everything backward needs goes through save_for_backward, outputs included: a tensor kept as a ctx
        # attribute that is also an output makes a cycle (output -> grad_fn -> ctx -> output) that only the
        # garbage collector frees, so memory grows step after step
        ctx.save_for_backward(q, used, a["V"], a["evals"], a["null"], PiN, a["N"], a["consistent"])
        ctx.mark_non_differentiable(a["consistent"], a["ref"])
        return At, qt, PiN, a["consistent"], a["ref"]

    @staticmethod
    @torch.autograd.function.once_differentiable  # (which torch types as making ctx positional-only)
    def backward(ctx, gA, gq, gPi, *_):  # noqa: D102  # pyright: ignore[reportIncompatibleMethodOverride]
        q, used, V, evals, null, PiN, N, consistent = ctx.saved_tensors
        mask = used[:, :, None] & used[:, None, :]
        k = consistent.to(q.dtype)[:, None, None]
        G = torch.where(mask, 0.5 * (gA + gA.mT), torch.zeros_like(gA))
        g = gq * used
        qs = q * used
        # Ã = A − Π_N A Π_N + k·ε·Π_N,  q̃ = q − k Π_N q:  the terms with dA and dq at fixed Π_N …
        grad_A = gA - torch.where(mask, PiN @ G @ PiN, torch.zeros_like(gA))
        grad_q = gq - k[..., 0] * (PiN @ g[..., None])[..., 0]
        # … and the terms of dΠ_N = Σ_{i flat, j not} (v_j v_jᵀ dA v_i v_iᵀ + transpose)/(λ_i − λ_j)
        H = gPi - (G @ N + N @ G) - k * g[..., None] * qs[:, None, :]
        X = V.mT @ (0.5 * (H + H.mT)) @ V
        pair = null[:, :, None] & ~null[:, None, :]  # (i flat, j not)
        F = torch.where(pair, 1.0 / (evals[:, :, None] - evals[:, None, :]).where(pair, torch.ones_like(X)), 0.0)
        Z = F * X
        Z = Z + Z.mT
        grad_A = grad_A + torch.where(mask, V @ Z @ V.mT, torch.zeros_like(gA))
        return grad_A, grad_q, None, None, None, None


@dataclass
class FlatSet:
    """The elements with flat directions (``project_flat``): indices idx (m,), their flat projectors Π_N
    (m, n, n), differentiable, and whether their q's flat part was rounding (m,) bool: those get the minimum-norm
    stage."""

    idx: torch.Tensor
    PiN: torch.Tensor
    consistent: torch.Tensor
    ref: torch.Tensor  # (m,) max diag of A on the rows in use (a constant)

    def subset(self, sel: torch.Tensor) -> FlatSet:
        """The elements ``sel`` (m,) bool of this set, renumbered 0 … sel.sum() − 1."""
        return FlatSet(
            torch.arange(int(sel.sum()), device=self.idx.device), self.PiN[sel], self.consistent[sel], self.ref[sel]
        )


def project_flat(A, q, mu, active, d, tol, found):
    """The problem data with flat directions resolved (module docstring) in the elements ``found``.

    A: (B, n, n), q: (B, n), mu, active: (B, K) tensors; tol: ``psd_tol`` of the input dtype; found: (B,) bool
    array, the elements with a flat direction (``flat_elements``), at least one.  Returns (A, q, flat): float64
    tensors (A symmetrised in the changed elements) and a ``FlatSet``.  Differentiable (``FlatProjection``).
    """
    used = rows_in_use(mu.detach(), active, d)
    A64 = A.to(torch.float64)
    q64 = q.to(torch.float64)
    idx = torch.from_numpy(found).nonzero().flatten()
    sym = 0.5 * (A64[idx] + A64[idx].mT)
    At, qt, PiN, consistent, ref = FlatProjection.apply(
        sym, q64[idx], used[idx], tol, idx, mu.detach()[idx].to(torch.float64)
    )
    return A64.index_copy(0, idx, At), q64.index_copy(0, idx, qt), FlatSet(idx, PiN, consistent, ref)


def centre_on(A, q, flat: FlatSet, sel, f_star):
    """A + ε·Π_N and q − ε·Π_N f* for the elements ``sel`` of ``flat`` (ε = ref): the problem whose unique
    minimiser is f*, a minimiser of (A, q) (the added term is zero, and least, only there).

    Its implicit gradient is well posed where the original one is not (a whole set of minimisers): with f* inside
    that set, the constraint that bounds it (zero multiplier) is inactive, so the derivative of the range part is
    the one of the original problem; ``minimum_norm``, applied afterwards, moves to the least-norm end and carries
    the derivative of that end.  f_star: (m', n) for the elements ``sel`` (m,) bool, in their order; a constant.
    """
    idx = flat.idx[sel]
    eps = flat.ref[sel][:, None, None]
    PiN = flat.PiN[sel]
    A = A.index_add(0, idx, eps * PiN)
    q = q.index_add(0, idx, -(eps * PiN @ f_star.detach()[..., None])[..., 0])
    return A, q


def minimum_norm(f, flat: FlatSet, mu, lower, active, d, solve, problem, sel=None):
    """Move the minimisers f of the elements in ``flat`` whose q had no flat part to the minimiser of least norm.

    Every minimiser has the range part r = Π_R f (Π_R = I − Π_N); the others are r + v, v in the flat space, inside
    the cones, and the least-norm one is the projection of 0 onto that set.  With one flat direction v (the
    gyroscope; a pendulum bob on the ground) these are the points f + t·v of an interval of t (``_line_interval``,
    closed form per contact), and the least norm is at t = −f·v/‖v‖² clipped to it.  With several, it is the
    solution of  min ½‖g‖²  over the cones with Π_R g = r, found by the augmented Lagrangian method on that
    equality (``_least_norm_several``): each step a strictly convex cone QP (``solve``), the error divided by
    about 1 + ``RHO`` per step, to the solver's accuracy.  Differentiable (torch operations and ``solve``).

    f: (B, n) float64; mu, lower: (B, K); active: (B, K) bool; solve(idx, A, q) → (g, status): the cone QP of the
    batch elements idx (m,) with A (m, n, n) and q (m, n), differentiable; problem: (A, q) of the batch, the
    problem (flat parts resolved) whose minimisers f are; sel: (m,) bool, the elements of ``flat`` to treat (default:
    the consistent ones).  Returns f with those rows replaced and the status of their
    least-norm stage ((m',) ``Status`` codes, in their order; 0 where it is in closed form).
    """
    sel = flat.consistent if sel is None else sel
    status = torch.zeros(len(flat.idx), dtype=torch.long, device=flat.idx.device)
    nullity = _nullity(flat.PiN)
    one = sel & (nullity == 1)
    if one.any():
        idx = flat.idx[one]
        f = f.index_copy(0, idx, _least_norm_one(f[idx], flat.PiN[one], mu[idx], lower[idx], active[idx], d)[0])
    several = sel & (nullity > 1)
    if several.any():
        idx = flat.idx[several]
        x, status[several], _ = _least_norm_several(idx, f[idx], flat.PiN[several], solve, problem)
        f = f.index_copy(0, idx, x)
    return f, status[sel]


def nonunique(f, flat: FlatSet, mu, lower, active, d, solve, first=None):
    """The consistent elements of ``flat`` whose minimisers f (B, n) are not unique, and a minimiser inside their
    set, on which ``centre_on`` centres the problem for a well-posed gradient.  One flat direction: where the line
    along it has width > UNIQUE_TOL·max(1, ‖f‖∞) in the cones (where it only touches the cones at f, a sliding
    contact whose flat direction is tangent to its cone, the minimiser is unique after all); the point halfway from
    the least-norm one to the far end or by max(1, ‖f‖∞).  Several: where the least-norm minimiser is farther than
    that from f, an interior-point solution (which lies away from the set's faces, so it is not the least-norm point
    of a set that is not a single point); f itself.  solve: as for ``minimum_norm``.  first (B, n), optional:
    another minimiser of each element (the first solve's, where ``problem._near_least_norm`` brought it back from far
    out to f, which can then be the least-norm point itself, so that the tests above see no width): farther from f
    than UNIQUE_TOL·max(1, ‖f‖∞), the set is not a point, and the point towards it (halfway, at most max(1, ‖f‖∞)/2
    away, as for one flat direction) is inside it.  Returns a mask (m,) over the elements of ``flat`` and the points
    (m', n) for the consistent ones; no gradient.
    """
    spread = torch.zeros(len(flat.idx), dtype=torch.bool, device=flat.idx.device)
    inner = f[flat.idx].detach().clone()
    nullity = _nullity(flat.PiN)
    one, several = flat.consistent & (nullity == 1), flat.consistent & (nullity > 1)
    if one.any():
        idx = flat.idx[one]
        _, spread[one], inner[one] = _least_norm_one(
            f[idx].detach(), flat.PiN[one], mu[idx], lower[idx], active[idx], d
        )
    if several.any():
        spread[several] = _least_norm_several(flat.idx[several], f[flat.idx[several]], flat.PiN[several], solve)[2]
    if first is not None:
        x, y = f[flat.idx].detach(), first[flat.idx].detach()
        size = x.abs().amax(-1, keepdim=True).clamp_min(1.0)
        gap = (y - x).abs().amax(-1, keepdim=True)
        missed = flat.consistent & ~spread & (gap[:, 0] > UNIQUE_TOL * size[:, 0])
        towards = x + 0.5 * torch.minimum(torch.ones_like(gap), size / gap.clamp_min(1e-300)) * (y - x)
        spread, inner = spread | missed, torch.where(missed[:, None], towards, inner)
    return spread, inner[flat.consistent]


def _nullity(PiN):
    return torch.diagonal(PiN, dim1=-2, dim2=-1).sum(-1).round().long()


def _least_norm_one(x, PiN, mu, lower, active, d):
    """``minimum_norm`` for elements with one flat direction: returns (x moved, spread (m,), inner (m, n))."""
    start = x.detach()
    # the flat direction: Π_N's column with the largest diagonal (Π_N = v vᵀ), normalised
    j = torch.diagonal(PiN, dim1=-2, dim2=-1).argmax(-1)
    v = PiN.gather(-1, j[:, None, None].expand(-1, x.shape[-1], 1))[..., 0]
    v = v / v.norm(dim=-1, keepdim=True)
    # a contact's part of v at the eigensolver's rounding is zero: near a cone's apex or face, those parts alone
    # (1e-17) set the interval's ends by ratios of rounding (a contact at its bound cut the move to 4 % of its
    # length, or to nothing, depending on the batch); moved by them the contact would change by less than rounding
    m, n = x.shape
    vk = v.view(m, -1, d)
    v = torch.where(vk.detach().abs().amax(-1, keepdim=True) <= V_ROUNDING, 0.0, vk).view(m, n)
    lo, hi = _line_interval(x, v, mu, lower, active, d)
    scale = start.abs().amax(-1).clamp_min(1.0)
    # a line that only touches the cones (tangent: its ends known to the square root of rounding) is no step
    spread = (hi - lo).detach() > UNIQUE_TOL * scale
    t = torch.minimum(torch.maximum(-(x * v).sum(-1), lo), hi)
    # a point halfway into the set of minimisers from the least one (``centre_on``)
    reach = 0.5 * torch.minimum(hi - lo, scale).detach()
    tc = torch.where(t <= lo, lo + reach, torch.where(t >= hi, hi - reach, t)).detach()
    inner = start + torch.where(spread, tc, 0.0)[:, None] * v.detach()
    return x + torch.where(spread, t, 0.0)[:, None] * v, spread, inner


def _least_norm_several(idx, x, PiN, solve, problem=None):
    """The least-norm point g of the cones with Π_R g = Π_R x (m elements, several flat directions): the augmented
    Lagrangian method on the equality, min ½‖g‖² + ½ρ‖Π_R g − w‖² over the cones with the target w moved by the
    miss Π_R x − Π_R g after each solve (the multiplier ρ(w − Π_R x) in disguise).  The penalised problem is strictly
    convex (Hessian I + ρΠ_R); its solution map, unrolled over the steps, carries the derivative, exact at the
    fixed point.  An element whose miss falls by less than 100× in a step (the cones' faces nearly parallel to the
    equality) has its ρ raised 10× up to ``RHO_MAX`` (beyond, the penalised problem is too ill-conditioned to solve
    to the accuracy needed); each element steps until its own miss is below ALM_TOL·max(1, ‖x‖∞), so that its
    result does not depend on its batch.

    Where the set of minimisers is a single point (the cones touch the flat space only there) the method stalls
    (its miss falls sublinearly); an element stops once its miss, falling at its last rate at ρ = RHO_MAX for the
    steps left, would not reach ALM_TOL (it ends as the remaining steps would, in 4–5 solves instead of
    ALM_STEPS on BP5's training problems).  An element whose iterate stalls ALM_FAR times farther from x than its
    miss is not at a point: there x is not the least-norm minimiser, and the iterate, near it but a minimiser only
    to its miss (measured up to 2e-7: the inner solves' accuracy at ρ = RHO_MAX, where the cones' faces are nearly
    parallel to the equality), steps on to ALM_FLOOR; it is then finished by one proximal step on the problem
    (``problem``: min ½fᵀAf + qᵀf + ½ε‖f − g‖², ε = PROX·max A_ii), which returns the minimiser next to it (to
    rounding: the pull adds ε times the miss), reported with that solve's status where the miss had reached
    ALM_FLOOR, else INACCURATE (a minimiser whose norm is least only to the miss); where that step raises the norm
    (its error along the flat directions) the iterate is kept if it is a minimiser to ALM_ACCEPT, with its last
    solve's status; without ``problem`` (or where that step fails) it keeps x, INACCURATE.  Any other element that
    has not converged keeps x: reported INACCURATE if its last iterate was a minimiser (miss ≤ ALM_ACCEPT) away from
    x, else 0 (the set is a point: x).  An
    element whose least-norm point is within UNIQUE_TOL·max(1, ‖x‖∞) of x keeps x (a set that is a point up to
    that).  Returns g (m, n), status (m,) (of its last solve where g is not x, else 0 or INACCURATE) and moved
    (m,) bool: the set of minimisers is not a point (g is not x, but where the proximal step failed)."""
    m, n = x.shape
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    PiR = eye - PiN
    r = (PiR @ x[..., None])[..., 0]
    scale = x.detach().abs().amax(-1).clamp_min(1.0)
    rho = torch.full((m,), RHO, dtype=x.dtype, device=x.device)
    w, g = r, x
    status = torch.zeros(m, dtype=torch.long, device=x.device)
    live = torch.ones(m, dtype=torch.bool, device=x.device)  # still stepping
    unconverged = torch.zeros(m, dtype=torch.bool, device=x.device)  # stopped as stalled
    size = torch.full((m,), torch.inf, dtype=x.dtype, device=x.device)
    steady = torch.zeros(m, dtype=torch.bool, device=x.device)  # ρ was at RHO_MAX in the step before, too
    for step in range(ALM_STEPS):
        at = live.nonzero().flatten()
        g_at, step_status = solve(idx[at], eye + rho[at, None, None] * PiR[at], -rho[at, None] * w[at])
        g = g.index_copy(0, at, g_at)
        status[at] = step_status
        miss = r - (PiR @ g[..., None])[..., 0]
        before, size = size, torch.where(live, miss.detach().abs().amax(-1), size)
        live = live & (size > ALM_TOL * scale)
        # stalled: at ρ = RHO_MAX, a miss that, falling at its last rate for every step left, would still be above
        # the tolerance at the end (the rate only worsens where the set is a point: the miss falls sublinearly)
        left = ALM_STEPS - 1 - step
        stalled = live & steady & (size * (size / before).clamp_max(1.0) ** left > ALM_TOL * scale)
        # ... but an iterate far from x (the set is not a point) steps on until it is a minimiser to the inner
        # solves' accuracy (ALM_FLOOR): x is not the least-norm point there
        far = (g.detach() - x.detach()).abs().amax(-1) >= ALM_FAR * size
        stalled = stalled & ~(far & (size > ALM_FLOOR * scale))
        unconverged, live = unconverged | stalled, live & ~stalled
        if not live.any():
            break
        grow = torch.where(live & (size > 1e-2 * before) & (rho < RHO_MAX), 10.0, 1.0)
        # (the multiplier ρ(w − r) is kept where ρ grows)
        w = torch.where(live[:, None], r + (w + miss - r) / grow[:, None], w)
        steady = rho >= RHO_MAX
        rho = rho * grow
    unconverged = unconverged | live
    dist = (g.detach() - x.detach()).abs().amax(-1)
    moved = dist > UNIQUE_TOL * scale
    far = unconverged & moved & (dist >= ALM_FAR * size)
    short = unconverged & moved & (size <= ALM_ACCEPT * scale)
    last = status.clone()  # (the last solve's)
    status = torch.where(moved & ~unconverged, status, torch.where(short | far, Status.INACCURATE, 0))
    taken = moved & ~unconverged
    if problem is not None and far.any():
        at = far.nonzero().flatten()
        A, q = problem[0][idx[at]], problem[1][idx[at]]
        eps = PROX * A.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(torch.finfo(x.dtype).tiny)
        g_at, prox_status = solve(idx[at], A + eps[:, None, None] * eye, q - eps[:, None] * g[at])
        # the step corrects the range part (x's, kept by the equality, can be off by x's accuracy at its size), but
        # its curvature ε makes it ill-conditioned along the flat directions, where it moves a point by its
        # residual / ε: a larger norm is that error (0.23 of 50 at a miss of 1.7e-10: degenerate fuzz K = 19, d = 2,
        # seed 1, element 159), and an iterate that is a minimiser to ALM_ACCEPT already is then kept as it is
        kept = (g_at.detach().norm(dim=-1) > g[at].detach().norm(dim=-1) * (1 + 1e-9)) & short[at]
        status[at[kept]] = last[at[kept]]
        taken[at[kept]] = True
        ok = ~is_failure(prox_status) & ~kept
        at, g_at, prox_status = at[ok], g_at[ok], prox_status[ok]
        g = g.index_copy(0, at, g_at)
        floor = size[at] <= ALM_FLOOR * scale[at]
        status[at] = torch.where(floor, prox_status, prox_status.clamp_min(Status.INACCURATE))
        taken[at] = True
    return torch.where(taken[:, None], g, x), status, moved & (~unconverged | far)


def _line_interval(f, v, mu, lower, active, d):
    """The interval [lo, hi] of t with f + t·v in the cones (f in them): (m,) each, ±inf where unbounded.

    Per contact: the ray f_n + t v_n ≥ lower, and (d > 1, μ > 0) the cone ‖f_t + t v_t‖ ≤ μ (f_n + t v_n), whose
    boundary points are the roots of a t² + 2b t + c = 0 with a = μ²v_n² − ‖v_t‖², b = μ² f_n v_n − f_t·v_t,
    c = μ² f_n² − ‖f_t‖² ≥ 0.  A line meets the convex cone in an interval around t = 0: between the roots if
    a < 0 (v outside the cone), beyond the root on the side of the cone (v_n's sign) if a > 0.
    """
    m, n = f.shape
    K = n // d
    fk, vk = f.view(m, K, d), v.view(m, K, d)
    inf = torch.full((m, K), torch.inf, dtype=f.dtype, device=f.device)
    fn, vn = fk[..., 0], vk[..., 0]
    tiny = 1e-12  # (|v_n| below: the bound is at t ~ rounding / 1e-12 or beyond; ignored)
    bound = (lower - fn) / torch.where(vn.abs() > tiny, vn, torch.ones_like(vn))
    lo = torch.where(active & (vn > tiny), bound, -inf)
    hi = torch.where(active & (vn < -tiny), bound, inf)
    if d > 1:
        ft, vt = fk[..., 1:], vk[..., 1:]
        a = mu**2 * vn**2 - (vt**2).sum(-1)
        b = mu**2 * fn * vn - (ft * vt).sum(-1)
        c = mu**2 * fn**2 - (ft**2).sum(-1)
        c = c - c.detach().clamp_max(0.0)  # (≥ 0 but for rounding, which must not cut the derivative)
        disc = b**2 - a * c
        sq = torch.where(disc > 0, torch.where(disc > 0, disc, 1.0).sqrt(), 0.0)  # (no NaN in the derivative)
        qq = -(b + torch.where(b >= 0, sq, -sq))  # roots qq/a and c/qq without cancellation
        safe = lambda x: torch.where(x != 0, x, torch.ones_like(x))  # noqa: E731
        r1 = torch.where(a != 0, qq / safe(a), torch.where(b != 0, -c / (2 * safe(b)), -inf))
        r2 = torch.where(qq != 0, c / safe(qq), r1)
        small, large = torch.minimum(r1, r2), torch.maximum(r1, r2)
        cone = active & (mu > 0)
        outside = a < -1e-12 * (mu**2 * vn**2 + (vt**2).sum(-1))  # v outside the cone: between the roots
        inside = ~outside & (sq > 0)  # beyond the root on the cone's side
        lo = torch.where(cone & outside, torch.maximum(lo, small), lo)
        hi = torch.where(cone & outside, torch.minimum(hi, large), hi)
        lo = torch.where(cone & inside & (vn > 0), torch.maximum(lo, large), lo)
        hi = torch.where(cone & inside & (vn < 0), torch.minimum(hi, small), hi)
    # x is inside up to rounding, so the interval holds t = 0: a bound on the wrong side by rounding is moved to 0
    # in value, keeping its derivative (x is often at the interval's end: the minimum-norm point found before)
    lo, hi = lo.amax(-1), hi.amin(-1)
    return lo - lo.detach().clamp_min(0.0), hi - hi.detach().clamp_max(0.0)
