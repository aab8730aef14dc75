"""The contact cone QP: input checks, scaling, and the public entry point ``solve_cone_qp``.

Problem (paper Eqs. 15 and 17), independently for every batch element:

    minimise ½ fᵀAf + qᵀf   subject to   f_n,i ≥ lower_i,  ‖f_t,i‖ ≤ μ_i f_n,i   for every active contact i.

The solver works on z with f = γ·S·D·z: D = diag(1, μ_i, …) per contact turns every friction cone into the
unit second-order cone (so μ = 0 needs no special case), S is a per-contact Jacobi scaling and γ a global scale
that bring the data to order one.  S and γ are constants of the scaling (the solution map is equivariant
under them), so they carry no gradient; D carries the gradient with respect to μ.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from diffcontact.errors import ContactSolverError
from diffcontact.solver import flat, ipm, scaling
from diffcontact.solver.exact import contact_dims
from diffcontact.solver.implicit import ImplicitConeQP, ScaledSolution
from diffcontact.solver.status import Status, is_failure


@dataclass
class SolverInfo:
    """What the solver reports besides the solution.

    status: (B,) int64 of :class:`Status` codes; iterations: (B,); residual: (B,) final scaled KKT residual.
    """

    status: torch.Tensor
    iterations: torch.Tensor
    residual: torch.Tensor

    @property
    def failed(self) -> torch.Tensor:
        """(B,) bool: elements whose solution is not usable (returned as zeros)."""
        return is_failure(self.status)

    @property
    def n_failed(self) -> int:
        """Number of failed elements."""
        return int(self.failed.sum())


def check_problem(A, q, mu, lower=None, active=None):
    """Validate shapes and values; returns (A, q, mu, lower, active, d) with defaults filled in.

    A: (B, K·d, K·d); q: (B, K·d); mu: (B, K) ≥ 0; lower: (B, K) ≥ 0 or None; active: (B, K) bool or None.
    """
    for name, t in (("A", A), ("q", q), ("mu", mu)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if A.dim() != 3 or A.shape[-1] != A.shape[-2]:
        raise ValueError(f"A must have shape (B, K*d, K*d), got {tuple(A.shape)}")
    B, n = A.shape[0], A.shape[-1]
    if mu.dim() != 2 or mu.shape[0] != B:
        raise ValueError(f"mu must have shape (B, K) with B = {B}, got {tuple(mu.shape)}")
    K = mu.shape[-1]
    if K == 0 or n % K != 0 or n // K not in (1, 2, 3):
        raise ValueError(f"A has {n} rows for K = {K} contacts: the contact dimension d = n/K must be 1, 2 or 3")
    d = n // K
    if tuple(q.shape) != (B, n):
        raise ValueError(f"q must have shape (B, K*d) = {(B, n)}, got {tuple(q.shape)}")
    if lower is None:
        lower = torch.zeros_like(mu)
    elif tuple(lower.shape) != (B, K):
        raise ValueError(f"lower must have shape (B, K) = {(B, K)}, got {tuple(lower.shape)}")
    if active is None:
        active = torch.ones(B, K, dtype=torch.bool, device=mu.device)
    elif tuple(active.shape) != (B, K) or active.dtype != torch.bool:
        raise ValueError(f"active must be a bool tensor of shape (B, K) = {(B, K)}")
    for name, t in (("A", A), ("q", q), ("mu", mu), ("lower", lower)):
        x = t.detach().numpy()  # (numpy reductions: a few µs where torch's cost tens on small batches)
        # (a finite sum is the fast test; an overflowing one falls through to the exact test)
        if not np.isfinite(x.sum()):
            bad = ~np.isfinite(x).reshape(B, -1).all(-1)
            if bad.any():
                raise ValueError(f"{name} has non-finite values in batch elements {_first(torch.from_numpy(bad))}")
        if name in ("mu", "lower") and x.size and x.min() < 0:
            negative = torch.from_numpy((x < 0).any(-1))
            raise ValueError(f"{name} must be >= 0; negative in batch elements {_first(negative)}")
    return A, q, mu, lower, active, d


def _first(mask: torch.Tensor, k: int = 10) -> str:
    idx = mask.nonzero().flatten().tolist()
    return str(idx[:k]) + (f" (and {len(idx) - k} more)" if len(idx) > k else "")


def solve_cone_qp(
    A: torch.Tensor,
    q: torch.Tensor,
    mu: torch.Tensor,
    lower: torch.Tensor | None = None,
    active: torch.Tensor | None = None,
    *,
    tol: float = 1e-10,
    acceptable_tol: float = 1e-7,
    max_iter: int = 60,
    on_failure: Literal["raise", "count"] = "raise",
    return_info: bool = False,
):
    """Solve a batch of contact cone QPs; differentiable by implicit differentiation.

    Args:
        A: (B, K·d, K·d) symmetric PSD inverse inertia in contact space, possibly singular and PSD only up to
            rounding: flat directions and non-unique minimisers are resolved as stated in ``solver/flat.py``
            (the minimiser of least norm); a genuinely indefinite A raises ``IndefiniteMatrixError``.
        q: (B, K·d) linear term (contact velocity, minus the target velocity in the restitution phase).
        mu: (B, K) friction coefficients ≥ 0 (unused for d = 1).
        lower: (B, K) lower bounds ≥ 0 on the normal impulses (restitution phase: e·f_n of compression).
        active: (B, K) bool; inactive contacts get f = 0 and do not affect the others.
        tol: target of the scaled KKT residual; acceptable_tol: residual still usable at the iteration limit.
        on_failure: "raise" raises :class:`ContactSolverError` naming the failing elements; "count" returns
            zeros for them and reports them in the info.
        return_info: also return a :class:`SolverInfo`.

    Returns:
        f: (B, K·d) in the dtype of A (solved in float64), or (f, info).  Contact i's entries are
        f[..., i·d:(i+1)·d] = (f_n, f_t…).  Gradients flow to A, q, mu and lower.
    """
    if on_failure not in ("raise", "count"):
        raise ValueError(f"on_failure must be 'raise' or 'count', got {on_failure!r}")
    A, q, mu, lower, active, d = check_problem(A, q, mu, lower, active)
    out_dtype = A.dtype if A.dtype.is_floating_point else torch.float64
    A, q, flats = flat.project_flat(A, q, mu, active, d, flat.psd_tol(out_dtype))
    opts = (tol, acceptable_tol, max_iter, on_failure)
    if flats is not None and flats.consistent.any():
        f, result = _solve_least_norm(A, q, mu, lower, active, d, flats, opts)
    else:
        f, result = _solve_differentiable(A, q, mu, lower, active, d, *opts)
    f = f.to(out_dtype)
    if return_info:
        return f, SolverInfo(status=result.status, iterations=result.iterations, residual=result.residual)
    return f


def _solve_least_norm(A, q, mu, lower, active, d, flats, opts):
    """Solve a batch some of whose elements have non-unique minimisers and return the least-norm ones
    (``solver/flat.py``): (f, result) as ``_solve_differentiable``.

    Without gradients: one solve, then the move to the least-norm minimiser.  With gradients, where the minimisers
    are not unique: any minimiser (first solve), a point inside their set, that point solved for again,
    differentiably, as the unique minimiser of the problem with curvature on the flat directions centred on it,
    and the move from there to the least-norm one (whose derivative is that of the cone bounding the set).
    """

    if torch.is_grad_enabled() and any(t.requires_grad for t in (A, q, mu, lower)):
        sub = flats.idx[flats.consistent]
        with torch.no_grad():
            first, first_result = _solve_differentiable(
                A[sub].detach(), q[sub].detach(), mu[sub], lower[sub], active[sub], d, *opts
            )
            spread, inner = flat.nonunique(
                first,
                flats.subset(flats.consistent),
                mu[sub],
                lower[sub],
                active[sub],
                d,
                _cone_qp(mu[sub], lower[sub], active[sub], d, opts),
            )
        nonunique = torch.zeros_like(flats.consistent)
        nonunique[flats.consistent] = spread
        A, q = flat.centre_on(A, q, flats, nonunique, inner[spread])
        f, result = _solve_differentiable(A, q, mu, lower, active, d, *opts)
        result.status[sub] = torch.maximum(result.status[sub], first_result.status)
        treated = nonunique
    else:
        f, result = _solve_differentiable(A, q, mu, lower, active, d, *opts)
        treated = flats.consistent
    f, status = flat.minimum_norm(f, flats, mu, lower, active, d, _cone_qp(mu, lower, active, d, opts), sel=treated)
    result.status[flats.idx[treated]] = torch.maximum(result.status[flats.idx[treated]], status)
    # (a failed element's zeros may have been moved along its flat directions)
    return torch.where(is_failure(result.status)[:, None], torch.zeros_like(f), f), result


def _cone_qp(mu, lower, active, d, opts):
    """solve(idx, A, q) → (f, status) of the elements idx of this batch with A (m, n, n), q (m, n): the cone QPs
    of the least-norm stage (``flat.minimum_norm``), differentiable."""

    def solve(idx, A, q):
        f, result = _solve_differentiable(A, q, mu[idx], lower[idx], active[idx], d, *opts)
        return f, result.status

    return solve


def _solve_differentiable(A, q, mu, lower, active, d, tol, acceptable_tol, max_iter, on_failure):
    """Solve (``_solve``), apply the failure policy, and return (f, result) with f differentiable."""
    B = q.shape[0]
    with torch.no_grad():
        sol, result = _solve(A, q, mu, lower, active, d, tol, acceptable_tol, max_iter)
    bad = is_failure(result.status)
    if bad.any() and on_failure == "raise":
        codes = {int(s): Status(int(s)).name for s in result.status[bad].unique()}
        raise ContactSolverError(
            f"contact solver failed for {int(bad.sum())} of {B} batch elements {_first(bad)} "
            f"(status {codes}); pass on_failure='count' to continue with zero impulses for them",
            status=result.status,
            failed=bad.nonzero().flatten().tolist(),
        )
    if not A.dtype.is_floating_point:
        A = A.to(torch.float64)
    return ImplicitConeQP.apply(A, q, mu, lower, sol), result


def _solve(A, q, mu, lower, active, d, tol, acceptable_tol, max_iter) -> tuple[ScaledSolution, ipm.IPMResult]:
    """Scale (f = γ·S·D·z, see ``scaling.py``), solve in z, and collect what the backward pass needs."""
    arrays = scaling.scale_batch(
        *(np.ascontiguousarray(t.detach().to(torch.float64).numpy()) for t in (A, q, mu, lower)),
        np.ascontiguousarray(active.numpy()),
        contact_dims(d),
    )
    A64, P, c, l_hat, T, S, gamma, sigma, lower_scale, on_q, on_l, zero_mu = map(torch.from_numpy, arrays)
    q64 = q.detach().to(torch.float64)

    def run(c, l_hat, sel, margin=ipm.START_MARGIN):
        args = tuple(a[sel] for a in (P, c, l_hat, on_q, on_l)) if sel is not None else (P, c, l_hat, on_q, on_l)
        kw = dict(tol=tol, acceptable_tol=acceptable_tol, max_iter=max_iter, start_margin=margin)
        return ipm.solve_ipm(*args, d, **kw)

    def keep_better(sel, res2):  # the elements of `sel` that res2 solved better; returns their indices
        better = res2.status < result.status[sel]
        idx = sel.nonzero().flatten()[better]
        for name in ("z", "status", "iterations", "residual", "s_l", "lam_l", "s_q", "lam_q"):
            getattr(result, name)[idx] = getattr(res2, name)[better]
        return idx

    result = run(c, l_hat, None)
    # Elements that did not converge from the default starting point are solved again from CVXOPT's, farther
    # inside the cones (slower on average, more robust: two rope and BD5 problems of the simulation benchmark).
    again = result.status != Status.CONVERGED
    if again.any():
        keep_better(again, run(c, l_hat, again, ipm.ROBUST_MARGIN))
    # A badly estimated solution size (nearly singular A) can stall the method: solve those elements once more
    # with the scale of the stalled iterate.
    retry = (result.status == Status.MAX_ITER) & torch.isfinite(result.z).all(-1)
    if retry.any():
        gamma2 = gamma.clone()
        gamma2[retry] = gamma[retry] * result.z[retry].abs().amax(-1).clamp_min(1e-6)
        ratio = (gamma / gamma2)[:, None]  # c, l̂ and ∂l̂/∂lower all scale with 1/γ
        idx = keep_better(retry, run(c * ratio, l_hat * ratio, retry, ipm.ROBUST_MARGIN))
        if len(idx):
            gamma[idx] = gamma2[idx]
            lower_scale[idx] *= ratio[idx]
    z = torch.where(is_failure(result.status)[:, None], torch.zeros_like(result.z), result.z)
    slide = torch.zeros_like(sigma)
    if d > 1 and zero_mu.any():
        z, speed = _frictionless_slide_limit(z, A64, q64, T, gamma, zero_mu, d)
        # At μ = 0⁺ a sliding contact's cone multiplier is its sliding speed ‖g_t‖ and adds μ‖g_t‖ to the normal
        # velocity, as a linear term −μ‖g_t‖ on f_n would: zero in value, it carries that part of ∂f/∂μ.
        slide = speed * sigma / gamma[:, None] * zero_mu
    sol = ScaledSolution(
        A=A64,
        q=q64,
        T=T,
        S=S,
        gamma=gamma,
        lower_scale=lower_scale,
        slide=slide,
        z=z,
        result=result,
    )
    return sol, result


def _frictionless_slide_limit(z, A, q, T, gamma, zero_mu, d):
    """For μ = 0 contacts, set the tangential z to its limit as μ → 0⁺: −z_n·ĝ_t; also return ‖g_t‖.

    g_t is the tangential contact velocity A f + q after the impulse and ĝ_t its direction.  The returned f does
    not change (f_t = μ z_t = 0), but the backward pass then gives the one-sided derivative with respect to μ.
    Returns z: (B, n) and the sliding speeds ‖g_t‖: (B, K) (0 where the contact sticks or μ > 0).
    """
    B, n = z.shape
    K = n // d
    f = gamma[:, None] * T * z
    g = ((A @ f.unsqueeze(-1)).squeeze(-1) + q).view(B, K, d)[..., 1:]
    g_norm = g.norm(dim=-1, keepdim=True)
    scale = (A.diagonal(dim1=-2, dim2=-1).abs().amax(-1) * f.abs().amax(-1) + q.abs().amax(-1))[:, None, None]
    sliding = (g_norm > 1e-9 * scale.clamp_min(1e-300)) & zero_mu[..., None]
    zk = z.view(B, K, d)
    zt = torch.where(sliding, -zk[..., :1] * g / g_norm.clamp_min(1e-300), zk[..., 1:])
    speed = torch.where(sliding[..., 0], g_norm[..., 0], torch.zeros_like(g_norm[..., 0]))
    return torch.cat([zk[..., :1], zt], -1).reshape(B, n), speed
