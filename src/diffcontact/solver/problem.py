"""The contact cone QP: input checks, the public entry point ``solve_cone_qp`` and the solver's retry policy
(``_solve_with_retries``, the one place that decides what is run again and what counts as converged).

Problem (paper Eqs. 15 and 17), independently for every batch element:

    minimise ½ fᵀAf + qᵀf   subject to   f_n,i ≥ lower_i,  ‖f_t,i‖ ≤ μ_i f_n,i   for every active contact i.

The solver works on z with f = γ·S·D·z: D = diag(1, μ_i, …) per contact turns every friction cone into the
unit second-order cone (so μ = 0 needs no special case), S is a per-contact Jacobi scaling and γ a global scale
that bring the data to order one.  S and γ are constants of the scaling (the solution map is equivariant
under them), so they carry no gradient; D carries the gradient with respect to μ.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, overload

import numpy as np
import torch
from numba import njit

from diffcontact.errors import ContactSolverError
from diffcontact.solver import kernel, least_norm, optimality, scaling
from diffcontact.solver.implicit import ImplicitConeQP, ScaledSolution
from diffcontact.solver.kkt import contact_dims
from diffcontact.solver.policy import POLICY
from diffcontact.solver.status import Status, is_failure

# The retry policy (``_solve_with_retries``): thresholds and their reasons in ``solver/policy.py``.
IPM_TOL, ROUNDING_TOL, POLISH_STEPS = POLICY.ipm_tol, POLICY.rounding_tol, POLICY.polish_steps
POLISH_RETRY_STEPS = POLICY.polish_retry_steps
START_MARGIN, ROBUST_MARGIN = POLICY.start_margin, POLICY.robust_margin
FAR, TIKHONOV, TIKHONOV_MAX, MU_CAP = POLICY.far, POLICY.tikhonov, POLICY.tikhonov_max, POLICY.mu_cap
# (plain ints: an IntEnum member costs a µs per access in Python 3.11)
_CONVERGED, _INACCURATE, _MAX_ITER = int(Status.CONVERGED), int(Status.INACCURATE), int(Status.MAX_ITER)
_NUMERICAL = int(Status.NUMERICAL)
assert _CONVERGED == 0  # (``not np.count_nonzero(status)``: all converged)
# (on the path of every call: ``np.count_nonzero`` where possible, 3× faster than ``.any()`` on small arrays)


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


#: The largest friction coefficient accepted (``POLICY.mu_max``): far beyond sticking (μ = 1e6 sticks wherever
#: f_n > 0), and far below the μ (about 1e160) at which the scaled problem overflows.
MU_MAX = POLICY.mu_max


@dataclass(frozen=True)
class ConeQP:
    """A batch of contact cone QPs as ``solve_cone_qp`` takes them, checked: A (B, n, n), q (B, n), mu (B, K), lower
    (B, K) or None, active (B, K) bool or None; ``d`` the dimension of every contact (n = K·d)."""

    A: torch.Tensor
    q: torch.Tensor
    mu: torch.Tensor
    lower: torch.Tensor | None
    active: torch.Tensor | None
    d: int

    def rows(self, rows: torch.Tensor) -> ConeQP:
        """The elements ``rows`` ((m,) int64)."""
        A, q, mu, lower, active = (None if t is None else t[rows] for t in (self.A, self.q, self.mu, self.lower,
                                                                            self.active))  # fmt: skip
        return ConeQP(A, q, mu, lower, active, self.d)  # type: ignore[arg-type]

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The float64 arrays A, q, mu, lower, active the solver works on (``_as_arrays``)."""
        return _as_arrays(self.A, self.q, self.mu, self.lower, self.active)

    def needs_graph(self) -> bool:
        """Whether f is differentiated: gradients enabled, and A, q, μ or lower requires one."""
        inputs = (self.A, self.q, self.mu, self.lower)
        return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in inputs)


@dataclass(frozen=True)
class SolveOptions:
    """How ``solve_cone_qp`` solves: the scaled KKT residual it aims at (``tol``) and the one still usable at the
    iteration limit (``acceptable_tol``), the limit (``max_iter``), and what a failure does (``on_failure``:
    "raise" or "count")."""

    tol: float
    acceptable_tol: float
    max_iter: int
    on_failure: str = "raise"

    def counting(self) -> SolveOptions:
        """The same options, counting failures (an inner solve whose failures the caller decides on)."""
        return dataclasses.replace(self, on_failure="count")


def check_problem(A, q, mu, lower=None, active=None):
    """Validate shapes and values; returns (A, q, mu, lower, active, d) with defaults filled in.

    A: (B, K·d, K·d); q: (B, K·d); mu: (B, K) in [0, MU_MAX]; lower: (B, K) ≥ 0 or None; active: (B, K) bool or
    None; half-precision tensors are refused (their solutions overflow).
    """
    d = _check_shapes(A, q, mu, lower, active)
    _check_values(*_as_arrays(A, q, mu, lower, active))
    lower = torch.zeros_like(mu) if lower is None else lower
    active = torch.ones(mu.shape, dtype=torch.bool, device=mu.device) if active is None else active
    return A, q, mu, lower, active, d


def _check_shapes(A, q, mu, lower, active) -> int:
    """The shape and type checks of ``check_problem``; returns the contact dimension d."""
    for name, t in (("A", A), ("q", q), ("mu", mu)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dtype in (torch.float16, torch.bfloat16):
            raise TypeError(f"{name} is {t.dtype}: the solver takes float32 or float64 (half precision overflows)")
    shape_A, shape_mu = tuple(A.shape), tuple(mu.shape)
    if len(shape_A) != 3 or shape_A[1] != shape_A[2]:
        raise ValueError(f"A must have shape (B, K*d, K*d), got {shape_A}")
    B, _, n = shape_A
    if len(shape_mu) != 2 or shape_mu[0] != B:
        raise ValueError(f"mu must have shape (B, K) with B = {B}, got {shape_mu}")
    K = shape_mu[1]
    if K == 0 or n % K != 0 or n // K not in (1, 2, 3):
        raise ValueError(f"A has {n} rows for K = {K} contacts: the contact dimension d = n/K must be 1, 2 or 3")
    if tuple(q.shape) != (B, n):
        raise ValueError(f"q must have shape (B, K*d) = {(B, n)}, got {tuple(q.shape)}")
    if lower is not None and tuple(lower.shape) != shape_mu:
        raise ValueError(f"lower must have shape (B, K) = {(B, K)}, got {tuple(lower.shape)}")
    if active is not None and (tuple(active.shape) != shape_mu or active.dtype != torch.bool):
        raise ValueError(f"active must be a bool tensor of shape (B, K) = {(B, K)}")
    return n // K


def _as_arrays(A, q, mu, lower, active):
    """The data the solver works on: C-contiguous numpy arrays, float64 (A, q, mu, lower: zeros if None) and bool
    (active: all True if None).  Views of float64 CPU tensors, copies otherwise."""
    A, q, mu = _float64(A), _float64(q), _float64(mu)
    lower = np.zeros(mu.shape) if lower is None else _float64(lower)
    if active is None:
        active = np.empty(mu.shape, dtype=np.bool_)
        active.fill(True)
    else:
        active = np.ascontiguousarray(active.numpy())
    return A, q, mu, lower, active


def _float64(t: torch.Tensor) -> np.ndarray:
    """A CPU tensor as a C-contiguous float64 array: a view where it is one already, else a copy."""
    return np.ascontiguousarray((t.detach() if t.requires_grad else t).numpy(), dtype=np.float64)


def _check_values(A, q, mu, lower, active, a_finite=None) -> float:
    """Raise ``ValueError`` naming the batch elements where A, q, mu or lower are not finite or mu, lower < 0
    (arrays of ``_as_arrays``); returns the largest μ (0 if there is none).  a_finite: (B,) bool, whether each
    element's A is finite, if known (``least_norm.flat_elements`` reads it in its pass over A), else A is read here."""
    mu_max = (
        _values_ok(A, q, mu, lower, _NOTHING) if a_finite is None else _values_ok(_NO_MATRIX, q, mu, lower, a_finite)
    )
    if mu_max == mu_max:  # (not NaN)
        return mu_max
    B = len(mu)
    for name, x in (("A", A), ("q", q), ("mu", mu), ("lower", lower)):
        bad = ~a_finite if name == "A" and a_finite is not None else ~np.isfinite(x).reshape(B, -1).all(-1)
        if bad.any():
            raise ValueError(f"{name} has non-finite values in batch elements {_first(bad)}")
        if name in ("mu", "lower") and (x < 0).any():
            raise ValueError(f"{name} must be >= 0; negative in batch elements {_first((x < 0).any(-1))}")
    if mu.size and mu.max() > MU_MAX:
        raise ValueError(f"mu must be <= {MU_MAX:g}; larger in batch elements {_first((mu > MU_MAX).any(-1))}")
    raise AssertionError("_values_ok and _check_values disagree")  # (unreachable)


_NO_MATRIX, _NOTHING = np.zeros((0, 0, 0)), np.zeros(0, dtype=np.bool_)  # (A checked by its flags a_finite, or not)


@njit(cache=True, nogil=True)
def _values_ok(A, q, mu, lower, a_finite):
    """The largest μ (0 if there is none) if A, q, mu, lower are finite, a_finite ((B,) bool, or empty) all True,
    0 ≤ mu ≤ ``MU_MAX`` and lower ≥ 0, else NaN (one pass, no temporaries)."""
    a = A.ravel()
    s0 = s1 = s2 = s3 = 0.0  # (four independent sums: four times the throughput of one)
    for i in range(0, len(a) - 3, 4):
        s0 += a[i] * 0.0  # (0 for finite x, NaN for ±inf and NaN)
        s1 += a[i + 1] * 0.0
        s2 += a[i + 2] * 0.0
        s3 += a[i + 3] * 0.0
    total = s0 + s1 + s2 + s3
    for x in a[len(a) - len(a) % 4 :]:
        total += x * 0.0
    for x in q.flat:
        total += x * 0.0
    for x in a_finite:
        total += 0.0 if x else np.nan
    mu_max = 0.0
    for x in mu.flat:
        total += x * 0.0 if 0 <= x <= MU_MAX else np.nan
        mu_max = max(mu_max, x)
    for x in lower.flat:
        total += x * 0.0 if x >= 0 else np.nan
    return mu_max if total == 0.0 else np.nan


def _first(mask, k: int = 10) -> str:
    """The first k indices where the (B,) bool array or tensor ``mask`` is True, as text."""
    idx = np.flatnonzero(np.asarray(mask)).tolist()
    return str(idx[:k]) + (f" (and {len(idx) - k} more)" if len(idx) > k else "")


@overload
def solve_cone_qp(
    A: torch.Tensor,
    q: torch.Tensor,
    mu: torch.Tensor,
    lower: torch.Tensor | None = ...,
    active: torch.Tensor | None = ...,
    *,
    tol: float = ...,
    acceptable_tol: float = ...,
    max_iter: int = ...,
    on_failure: Literal["raise", "count"] = ...,
    flat_tol: float | None = ...,
    return_info: Literal[False] = ...,
) -> torch.Tensor: ...
@overload
def solve_cone_qp(
    A: torch.Tensor,
    q: torch.Tensor,
    mu: torch.Tensor,
    lower: torch.Tensor | None = ...,
    active: torch.Tensor | None = ...,
    *,
    tol: float = ...,
    acceptable_tol: float = ...,
    max_iter: int = ...,
    on_failure: Literal["raise", "count"] = ...,
    flat_tol: float | None = ...,
    return_info: Literal[True],
) -> tuple[torch.Tensor, SolverInfo]: ...
def solve_cone_qp(
    A: torch.Tensor,
    q: torch.Tensor,
    mu: torch.Tensor,
    lower: torch.Tensor | None = None,
    active: torch.Tensor | None = None,
    *,
    tol: float = POLICY.tol,
    acceptable_tol: float = POLICY.acceptable_tol,
    max_iter: int = POLICY.max_iter,
    on_failure: Literal["raise", "count"] = "raise",
    flat_tol: float | None = None,
    return_info: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, SolverInfo]:
    """Solve a batch of contact cone QPs; differentiable by implicit differentiation.

    The solver runs on the CPU in float64: the inputs become float64 numpy arrays once, after the shape checks, and
    everything up to the autograd Function works on them (the compiled kernel included); torch tensors only at
    the two ends (and in the rare elements with flat directions, whose projection is a differentiable torch
    operation).  Tensors on another device are copied to the CPU and f is copied back to their device (gradients
    flow through the copies); the info stays on the CPU.  Without gradients (``torch.no_grad()`` or no input that
    requires one) no autograd Function is made.

    Args:
        A: (B, K·d, K·d) symmetric PSD inverse inertia in contact space, possibly singular and PSD only up to
            rounding: flat directions and non-unique minimisers are resolved as stated in ``solver/least_norm.py``
            (the minimiser of least norm); a genuinely indefinite A raises ``IndefiniteMatrixError``.
        q: (B, K·d) linear term (contact velocity, minus the target velocity in the restitution phase).
        mu: (B, K) friction coefficients ≥ 0 (unused for d = 1).
        lower: (B, K) lower bounds ≥ 0 on the normal impulses (restitution phase: e·f_n of compression).
        active: (B, K) bool; inactive contacts get f = 0 and do not affect the others.
        tol: target of the scaled KKT residual; acceptable_tol: residual still usable at the iteration limit.
        on_failure: "raise" raises :class:`ContactSolverError` naming the failing elements; "count" returns
            zeros for them and reports them in the info.
        flat_tol: τ of ``solver/least_norm.py``: an eigenvalue of A within τ (relative) of zero is rounding, a flat
            direction; default ``least_norm.psd_tol`` of A's dtype, max(1e-6, 100·eps), which allows for an A of float32
            accuracy.  An A known to be accurate to float64 can pass less (the contact model does for a system
            without joints: ``POLICY.wide_flat_tol``).
        return_info: also return a :class:`SolverInfo`.

    Returns:
        f: (B, K·d) in the dtype of A (solved in float64), or (f, info).  Contact i's entries are
        f[..., i·d:(i+1)·d] = (f_n, f_t…).  Gradients flow to A, q, mu and lower.
    """
    if on_failure not in ("raise", "count"):
        raise ValueError(f"on_failure must be 'raise' or 'count', got {on_failure!r}")
    if not (0 < tol <= acceptable_tol < 1):  # (False for NaN)
        raise ValueError(f"tol = {tol!r}, acceptable_tol = {acceptable_tol!r}: need 0 < tol <= acceptable_tol < 1")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter = {max_iter!r} is not an integer >= 1")
    if flat_tol is not None and not (0 < flat_tol < 1):  # (False for NaN)
        raise ValueError(f"flat_tol = {flat_tol!r}: need 0 < flat_tol < 1")
    device = A.device if isinstance(A, torch.Tensor) else torch.device("cpu")
    if device.type != "cpu":
        A, q, mu = (t.cpu() if isinstance(t, torch.Tensor) else t for t in (A, q, mu))
        lower, active = (t.cpu() if isinstance(t, torch.Tensor) else t for t in (lower, active))
    d = _check_shapes(A, q, mu, lower, active)
    arrays = _as_arrays(A, q, mu, lower, active)
    out_dtype = A.dtype if A.dtype.is_floating_point else torch.float64
    opts = SolveOptions(tol, acceptable_tol, max_iter, on_failure)
    tau = least_norm.psd_tol(out_dtype) if flat_tol is None else flat_tol
    found, a_finite, symmetric = least_norm.flat_elements(arrays[0], arrays[2], arrays[4], d, tau)
    mu_max = _check_values(*arrays, a_finite)
    if np.count_nonzero(found):  # (rare: the elements with flat directions, in torch)
        lower = torch.from_numpy(arrays[3]) if lower is None else lower
        active = torch.from_numpy(arrays[4])
        A, q, flats = least_norm.project_flat(A, q, mu, active, d, tau, found)
        qp = ConeQP(A, q, mu, lower, active, d)
        if flats.consistent.any():
            # (the policy applied once at the end: a failed first solve may still be rescued, _near_least_norm)
            f, result = _solve_least_norm(qp, flats, opts.counting())
            _raise_on_failure(result.status, opts.on_failure)
        else:
            f, result = _solve_with_retries(qp, opts)
    else:
        qp = ConeQP(A, q, mu, lower, active, d)
        f, result = _solve_with_retries(qp, opts, arrays=arrays, mu_max=mu_max, symmetric=symmetric)
    if f.dtype != out_dtype or device.type != "cpu":
        f = f.to(device=device, dtype=out_dtype)
    if return_info:
        from_numpy = torch.from_numpy
        return f, SolverInfo(from_numpy(result.status), from_numpy(result.iterations), from_numpy(result.residual))
    return f


def _solve_with_retries(qp: ConeQP, opts: SolveOptions, arrays=None, mu_max=None, symmetric=None):
    """``_solve_scaled``, then ``_solve_sliding`` where a contact with μ ≥ ``scaling.MU_FREE`` slides, and the failure
    policy (``opts.on_failure``); returns (f, result) as ``_solve_scaled``."""
    f, result, outside = _solve_scaled(qp, opts, arrays=arrays, mu_max=mu_max, symmetric=symmetric)
    if outside is not None and outside.any():
        f = _solve_sliding(qp, opts, outside, f, result)
    _raise_on_failure(result.status, opts.on_failure)
    return f, result


def _solve_sliding(qp: ConeQP, opts: SolveOptions, outside: np.ndarray, f: torch.Tensor, result) -> torch.Tensor:
    """The elements of f (B, n) with contacts ``outside`` ((B, K) bool) their cone, solved again with those contacts
    scaled for sliding (``scaling.py``); their rows of f and of result's status, iterations and residual replaced.
    An answer is checked by its natural residual with every contact's true μ (one left free may have moved out of
    its cone): above ``acceptable_tol`` it becomes MAX_ITER (zeros).  Returns f."""
    rows = np.flatnonzero(outside.any(-1))
    r = torch.from_numpy(rows)
    part = qp.rows(r)
    again, sub, _ = _solve_scaled(part, opts, sliding=np.ascontiguousarray(outside[rows]))
    A64, q64, mu64, lower64, active64 = part.arrays()
    usable = np.flatnonzero(sub.status <= _INACCURATE)
    natural = optimality.natural_residual(
        0.5 * (A64 + A64.swapaxes(1, 2)), q64, mu64, lower64, active64, again.detach().double().numpy(), qp.d, usable
    )
    sub.status[usable[natural > opts.acceptable_tol]] = _MAX_ITER  # (a failure, not a wrong answer)
    failed = torch.from_numpy(is_failure(sub.status))[:, None]
    again = torch.where(failed, torch.zeros_like(again), again)
    for name in ("status", "iterations", "residual"):
        getattr(result, name)[rows] = getattr(sub, name)
    return f.index_copy(0, r, again.to(f.dtype))


@dataclass
class _Batch:
    """A batch as its attempts see it: the problems (the float64 arrays of ``_as_arrays``, A symmetrised), their
    scaling (``scaling.scale_batch``: f = γ·T⊙z; ``gamma`` and ``lower_scale`` change where an attempt rescales) and
    the options it is solved with."""

    A: np.ndarray  # (B, n, n) ½(A + Aᵀ)
    q: np.ndarray
    mu: np.ndarray
    lower: np.ndarray
    active: np.ndarray
    d: int
    c: np.ndarray  # the scaled problems' data (``scaling.scale_batch``)
    l_hat: np.ndarray
    T: np.ndarray
    S: np.ndarray
    gamma: np.ndarray
    sigma: np.ndarray
    lower_scale: np.ndarray
    on_q: np.ndarray
    on_l: np.ndarray
    zero_mu: np.ndarray
    opts: SolveOptions
    free: np.ndarray | None  # (B, K) contacts with μ ≥ ``scaling.MU_FREE`` scaled free (their cone comes after)
    mu_check: np.ndarray  # μ of the natural-residual checks (contacts scaled free: 1e300)
    check: bool  # some μ above ``optimality.MU_CHECKED``: usable answers are also checked in unscaled units

    @property
    def passes(self) -> list[dict]:
        """The kernel's passes: their tolerances (``IPM_TOL`` first where ``tol`` is below it)."""
        tol = self.opts.tol
        first = [dict(ipm_tol=IPM_TOL, final_tol=min(tol, ROUNDING_TOL))] if tol < IPM_TOL else []
        return [*first, dict(ipm_tol=tol, final_tol=tol)]

    def options(self, polish_steps: int = POLISH_STEPS) -> dict:
        """The kernel's options (the same in every pass)."""
        o = self.opts
        return dict(acceptable_tol=o.acceptable_tol, max_iter=o.max_iter, refine_tol=IPM_TOL, polish_steps=polish_steps)

    def result(self) -> kernel.IPMResult:
        """An empty kernel result for the batch."""
        return kernel.IPMResult(self.A, self.T, self.on_q, self.on_l, self.d)

    def solve(
        self, elements: np.ndarray, start_margin: float, out: kernel.IPMResult, c=None, l_hat=None,
        polish_steps: int = POLISH_STEPS,
    ) -> None:  # fmt: skip
        """The kernel's passes on ``elements`` into ``out`` (c, l_hat: of another γ; default the batch's)."""
        c, l_hat = (self.c, self.l_hat) if c is None else (c, l_hat)
        _solve_passes(self.A, self.T, c, l_hat, self.on_q, self.on_l, self.d, elements, self.passes,
                      self.options(polish_steps), start_margin, out)  # fmt: skip

    def natural(self, gamma: np.ndarray, z: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The relative natural residuals (``optimality.natural_residual``, with ``mu_check``) of the answers
        f = γ·T⊙z of the elements ``rows`` ((m,) int64); returns (m,)."""
        if not len(rows):
            return np.zeros(0)
        f = np.zeros_like(z)
        f[rows] = gamma[rows, None] * self.T[rows] * z[rows]
        return optimality.natural_residual(self.A, self.q, self.mu_check, self.lower, self.active, f, self.d, rows)


def _solve_scaled(qp: ConeQP, opts: SolveOptions, arrays=None, mu_max=None, sliding=None, symmetric=None):
    """Solve the batch ``qp`` with the retry policy below; returns (f (B, n) float64, differentiable
    (``ImplicitConeQP``) where an input requires a gradient, the kernel's ``IPMResult``, and (B, K) bool: the
    contacts scaled free whose answer leaves their cone, or None).  arrays: ``qp.arrays()`` if made already; the
    solver works on them, the tensors are only the ends of the autograd graph; mu_max: the largest μ if known
    (``_check_values``).  sliding: (B, K) bool, contacts with μ ≥ ``scaling.MU_FREE`` scaled for sliding, or None.
    symmetric: (B,) bool, where A equals its transpose exactly, if known (``least_norm.flat_elements``: with
    ``arrays``).

    The data are scaled once (f = γ·S·D·z, ``scaling.py``); every attempt then runs the compiled interior-point
    method with polishing (``kernel.solve``) on some elements, in up to two passes:

    - pass 1: the method to ``IPM_TOL``, then polishing; converged if that reaches rounding level (``ROUNDING_TOL``,
      or ``tol`` if larger);
    - pass 2, for the elements that did not (status INACCURATE or MAX_ITER, not a numerical failure): the method
      to ``tol`` itself, then polishing; converged if the residual is at most ``tol`` (a degenerate solution, where
      polishing stalls).  Where pass 1 ended with the lower residual, its answer is kept, judged by the same rule
      (a flat direction: polishing from pass 1's start got nearer than pass 2 does).  Without pass 2 where
      ``tol`` ≥ ``IPM_TOL``: pass 1 runs to ``tol``.

    The stages, each on the elements the ones before left unsolved: ``_default_start``, ``_robust_start``,
    ``_polished_longer``, ``_rescaled_start`` and ``_solve_capped`` (each says what it does and why); failed elements
    (``status.is_failure``) get z = 0.
    """
    batch = _scaled_batch(qp.arrays() if arrays is None else arrays, qp.d, opts, mu_max, sliding, symmetric)
    result = _default_start(batch)
    if np.count_nonzero(result.status) or batch.check:  # (all CONVERGED and nothing to check: the common case)
        _robust_start(batch, result)
        _polished_longer(batch, result)
        _rescaled_start(batch, result)
    outside = None
    if batch.free is not None and sliding is None:  # (contacts scaled free: their answer may leave the cone)
        outside = scaling.outside_cones(result.z, batch.mu, batch.free, qp.d) & (result.status <= _INACCURATE)[:, None]
    capped = None  # ((B, K) bool: contacts of answers solved with μ capped)
    if batch.check:
        capped = np.zeros(batch.mu.shape, dtype=bool)
        _solve_capped(batch, result, capped)
    return _answer(qp, batch, result, capped), result, outside


def _scaled_batch(arrays, d: int, opts: SolveOptions, mu_max=None, sliding=None, symmetric=None) -> _Batch:
    """The ``_Batch`` of the problems ``arrays`` (``ConeQP.arrays``) of contact dimension ``d``: scaled once, with
    the checks that large friction coefficients need (``mu_max``, their largest μ, if known; 0: none)."""
    A64, q64, mu64, lower64, active64 = arrays
    A64, c, l_hat, T, S, gamma, sigma, lower_scale, on_q, on_l, zero_mu = scaling.scale_batch(
        A64, q64, mu64, lower64, active64, contact_dims(d), sliding, symmetric
    )
    free, mu_check = None, mu64
    if d == 1:  # (μ is unused)
        mu_max = 0.0
    elif mu_max is None:
        mu_max = mu64.max() if mu64.size else 0.0
    if mu_max >= scaling.MU_FREE:  # (contacts with μ ≥ MU_FREE scaled free, checked as such: their cone comes after)
        free = active64 & (mu64 >= scaling.MU_FREE) & (True if sliding is None else ~sliding)
        mu_check = np.where(free, 1e300, mu64)
    check = bool(mu_max > optimality.MU_CHECKED)
    return _Batch(A64, q64, mu64, lower64, active64, d, c, l_hat, T, S, gamma, sigma, lower_scale, on_q, on_l,
                  zero_mu, opts, free, mu_check, check)  # fmt: skip


def _default_start(batch: _Batch) -> kernel.IPMResult:
    """Stage 1: every element from the default start (``START_MARGIN``, measured fastest)."""
    result = batch.result()
    batch.solve(np.arange(len(batch.gamma)), START_MARGIN, result)
    return result


def _keep_better(result: kernel.IPMResult, out: kernel.IPMResult, rows: np.ndarray) -> None:
    for name in kernel.IPMResult.OUTPUTS:
        getattr(result, name)[rows] = getattr(out, name)[rows]


def _robust_start(batch: _Batch, result: kernel.IPMResult) -> None:
    """Stage 2: the elements not converged, again from CVXOPT's start, farther inside the cones (``ROBUST_MARGIN``;
    two rope and BD5 problems of the simulation benchmark need it); an answer replaces the element's where its
    status is better (lower)."""
    elements = np.flatnonzero(result.status != _CONVERGED)
    if not len(elements):
        return
    out = batch.result()
    batch.solve(elements, ROBUST_MARGIN, out)
    _keep_better(result, out, elements[out.status[elements] < result.status[elements]])


def _rescaled_start(batch: _Batch, result: kernel.IPMResult) -> None:
    """Stage 4, from the robust start with another γ: the elements still at MAX_ITER with a finite iterate, with γ
    set to the size of the stalled iterate (a badly estimated solution size, nearly singular A, can stall the
    method); and the usable answers of elements with a friction coefficient above ``optimality.MU_CHECKED`` whose
    natural residual in unscaled units (``optimality.py``; contacts scaled free checked as free) exceeds
    ``acceptable_tol``, with γ set to γ·min(1, ‖z‖∞) (a guard: none at μ 10 … 1e3 since γ is estimated without the
    factor μ).  Its answer replaces theirs where usable with a lower natural residual, and those still above
    ``acceptable_tol`` become MAX_ITER (a failure, never a wrong answer); so do the answers of stalled elements
    (every μ) above it.  Otherwise an answer replaces the element's only where its status is better."""
    acceptable_tol, gamma = batch.opts.acceptable_tol, batch.gamma
    elements, gamma_try, stalled, wrong, natural = _rescaled_elements(batch, result)
    if not len(elements):
        return
    ratio = (gamma / gamma_try)[:, None]  # c, l̂ and ∂l̂/∂lower all scale with 1/γ
    out = batch.result()
    batch.solve(elements, ROBUST_MARGIN, out, batch.c * ratio, batch.l_hat * ratio)
    better = (out.status[elements] < result.status[elements]) & ~wrong[elements]
    again = elements[wrong[elements] & (out.status[elements] <= _INACCURATE)]
    now = batch.natural(gamma_try, out.z, again)
    better[np.searchsorted(elements, again[now < natural[again]])] = True
    natural[again] = np.minimum(now, natural[again])
    better = elements[better]
    _keep_better(result, out, better)
    batch.lower_scale[better] *= gamma[better, None] / gamma_try[better, None]
    gamma[better] = gamma_try[better]
    # (answers of stalled elements, every μ: their γ came from an iterate that may have run away along an unbounded
    # ray, A = 0 with q outside the dual cone; the scaled c then falls below the kernel's tolerance, absolute where
    # ‖z‖∞ < 1, and noise near z = 0 passes it)
    fresh = better[stalled[better]]
    natural[fresh] = batch.natural(gamma, result.z, fresh)
    result.status[natural > acceptable_tol] = _MAX_ITER  # (a failure, not a wrong answer)


def _polished_longer(batch: _Batch, result: kernel.IPMResult) -> None:
    """Stage 3: the elements still INACCURATE or at MAX_ITER with a finite iterate, from the default start with
    ``POLISH_RETRY_STEPS`` factorisations of polishing; an answer replaces the element's where its status is better.
    Where a contact's minimiser sits on the edge at which its lower bound cuts its cone (restitution after a learned
    e near 0: a bound 1e-4 of the answer's size), the method stalls near 3e-7 (its Newton systems lose accuracy as
    the gap closes) and Newton's polishing from there converges slowly at first: 5 factorisations reach rounding
    where the usual 3 end at 2.7e-7, MAX_ITER (``tests/data/lower_bound_edge.npz``)."""
    finite = np.isfinite(result.z).all(-1)
    elements = np.flatnonzero(((result.status == _INACCURATE) | (result.status == _MAX_ITER)) & finite)
    if not len(elements):
        return
    out = batch.result()
    batch.solve(elements, START_MARGIN, out, polish_steps=POLISH_RETRY_STEPS)
    _keep_better(result, out, elements[out.status[elements] < result.status[elements]])


def _rescaled_elements(batch: _Batch, result: kernel.IPMResult) -> tuple[np.ndarray, ...]:
    """The elements of ``_rescaled_start`` ((m,) int64) and the batch's γ with theirs changed (B,); which elements
    have stalled and which answers are wrong (B,) bool; the natural residuals of the checked answers (B,), 0 where
    not checked."""
    size = np.abs(result.z).max(-1)
    stalled = (result.status == _MAX_ITER) & np.isfinite(size)
    n = len(batch.gamma)
    high_mu = (batch.mu > optimality.MU_CHECKED).any(-1) if batch.check else np.zeros(n, dtype=bool)
    checked = np.flatnonzero((result.status <= _INACCURATE) & high_mu)
    natural = np.zeros(n)
    natural[checked] = batch.natural(batch.gamma, result.z, checked)
    wrong = natural > batch.opts.acceptable_tol  # (the answer is inaccurate in the problem's own units)
    elements = np.flatnonzero(stalled | wrong)
    gamma_try = batch.gamma.copy()
    if len(elements):
        factor = np.where(wrong, np.where(size > 0, np.minimum(size, 1.0), 1e-6), np.maximum(size, 1e-6))
        gamma_try[elements] *= factor[elements]
    return elements, gamma_try, stalled, wrong, natural


def _answer(qp: ConeQP, batch: _Batch, result: kernel.IPMResult, capped) -> torch.Tensor:
    """f (B, n) float64 of the solved batch: failed elements zero, the μ = 0⁺ sliding limit of frictionless
    contacts, and differentiable (``ImplicitConeQP``) where an input requires a gradient."""
    d = batch.d
    z = result.z
    if np.count_nonzero(result.status):
        failed = is_failure(result.status)
        if np.count_nonzero(failed):
            z = np.where(failed[:, None], 0.0, z)
    slide = None
    if d > 1 and np.count_nonzero(batch.zero_mu):
        z, speed = _frictionless_slide_limit(z, batch.A, batch.q, batch.T, batch.gamma, batch.zero_mu, d)
        # At μ = 0⁺ a sliding contact's cone multiplier is its sliding speed ‖g_t‖ and adds μ‖g_t‖ to the normal
        # velocity, as a linear term −μ‖g_t‖ on f_n would: zero in value, it carries that part of ∂f/∂μ.
        slide = speed * batch.sigma / batch.gamma[:, None] * batch.zero_mu
    if not qp.needs_graph():
        return torch.from_numpy(scaling.unscale(batch.gamma, batch.T, z))
    if slide is None:
        slide = np.zeros(batch.sigma.shape)
    sol = ScaledSolution(batch.A, batch.q, batch.T, batch.S, batch.gamma, batch.lower_scale, slide, z, result)
    A, mu = qp.A if qp.A.dtype.is_floating_point else qp.A.to(torch.float64), qp.mu
    if capped is not None and capped.any():  # (∂f/∂μ of the capped problem is not ours: 0 beyond the cap, as if stuck)
        mu = torch.where(torch.from_numpy(capped), mu.detach(), mu)
    return ImplicitConeQP.apply(A, qp.q, mu, qp.lower, sol)


def _solve_capped(batch: _Batch, result: kernel.IPMResult, capped: np.ndarray) -> None:
    """The last stage: the elements still at MAX_ITER with some μ > ``MU_CAP`` solved with μ capped at ``MU_CAP``
    (a scaled problem far better conditioned); an answer replaces theirs (in ``result`` and the batch's scaling T, S,
    gamma, sigma, lower_scale, in place) only where it is usable and passes the natural-residual check of the
    problem with the true μ, and ``capped`` (B, K) marks its contacts beyond the cap.  (Exact where those contacts
    stick or separate; a contact sliding at the cap fails the check unless the difference is below
    ``acceptable_tol``.)"""
    mu = batch.mu
    rows = np.flatnonzero((result.status == _MAX_ITER) & (mu > MU_CAP).any(-1))
    if not len(rows):
        return
    arrays = (batch.A[rows], batch.q[rows], np.minimum(mu[rows], MU_CAP), batch.lower[rows], batch.active[rows])
    # (no contact scaled free and no check inside: the capped answers are checked here, against the true μ)
    sub = dataclasses.replace(_scaled_batch(arrays, batch.d, batch.opts, mu_max=0.0), mu_check=mu[rows])
    out, every = sub.result(), np.arange(len(rows))
    sub.solve(every, START_MARGIN, out)
    ok = (out.status <= _INACCURATE) & (sub.natural(sub.gamma, out.z, every) <= batch.opts.acceptable_tol)
    take = rows[ok]
    for name in kernel.IPMResult.OUTPUTS:
        getattr(result, name)[take] = getattr(out, name)[ok]
    for name in ("T", "S", "gamma", "sigma", "lower_scale"):
        getattr(batch, name)[take] = getattr(sub, name)[ok]
    capped[take] = mu[take] > MU_CAP


def _raise_on_failure(status: np.ndarray, on_failure: str) -> None:
    """The failure policy: raise ``ContactSolverError`` naming the failed elements if ``on_failure`` is "raise"."""
    if on_failure != "raise" or not np.count_nonzero(status):  # (all converged: the common case)
        return
    failed = is_failure(status)
    if np.count_nonzero(failed):
        codes = {int(s): Status(int(s)).name for s in np.unique(status[failed])}
        raise ContactSolverError(
            f"contact solver failed for {int(failed.sum())} of {len(status)} batch elements "
            f"{_first(failed)} (status {codes}); pass on_failure='count' to continue with zero "
            "impulses for them",
            status=torch.from_numpy(status),
            failed=np.flatnonzero(failed).tolist(),
        )


def _solve_least_norm(qp: ConeQP, flats, opts: SolveOptions):
    """Solve a batch some of whose elements have non-unique minimisers and return the least-norm ones
    (``solver/least_norm.py``): (f, result) as ``_solve_with_retries``.

    Without gradients: one solve, then the move to the least-norm minimiser.  With gradients, where the minimisers
    are not unique: any minimiser (first solve), a point inside their set, that point solved for again,
    differentiably, as the unique minimiser of the problem with curvature on the flat directions centred on it,
    and the move from there to the least-norm one (whose derivative is that of the cone bounding the set).
    Either way a first minimiser far out along an unbounded set of minimisers is brought back first
    (``_near_least_norm``).
    """
    # (the flat stage in float64 whatever the input: μ² of a float32 μ ≥ 2e19 overflows, NaN in its gradient)
    lower, active, d = qp.lower, qp.active, qp.d
    assert lower is not None and active is not None  # (``solve_cone_qp`` made them)
    mu, lower = qp.mu.to(torch.float64), lower.to(torch.float64)
    qp = dataclasses.replace(qp, mu=mu, lower=lower)
    if qp.needs_graph():
        sub = flats.idx[flats.consistent]
        with torch.no_grad():
            part = ConeQP(qp.A[sub].detach(), qp.q[sub].detach(), mu[sub], lower[sub], active[sub], d)
            first, first_result = _solve_with_retries(part, opts)
            failed = is_failure(first_result.status)
            near = _near_least_norm(part, flats.subset(flats.consistent), first, first_result, opts)
            rescued = torch.from_numpy(failed & ~is_failure(first_result.status))
            spread, inner = least_norm.nonunique(
                near, flats.subset(flats.consistent), mu[sub], lower[sub], active[sub], d, _cone_qp(part, opts),
                first=first,
            )  # fmt: skip
        nonunique, centred = torch.zeros_like(flats.consistent), torch.zeros_like(flats.consistent)
        nonunique[flats.consistent] = spread
        # (and where the first solve failed and the one with curvature did not, the problem as it is would fail
        # again: centred on that answer, it has the same minimiser and curvature on its flat directions)
        centred[flats.consistent] = spread | rescued
        A, q = least_norm.centre_on(qp.A, qp.q, flats, centred, inner[spread | rescued])
        f, result = _solve_with_retries(dataclasses.replace(qp, A=A, q=q), opts)
        result.status[sub.numpy()] = np.maximum(result.status[sub.numpy()], first_result.status)
        treated = nonunique
    else:
        f, result = _solve_with_retries(qp, opts)
        treated = flats.consistent
        f = _near_least_norm(qp, flats, f, result, opts)
    # (the minimisers of qp's A, q are sought, not of the centred ones)
    f, status = least_norm.minimum_norm(f, flats, mu, lower, active, d, _cone_qp(qp, opts), (qp.A, qp.q), sel=treated)
    rows = flats.idx[treated].numpy()
    result.status[rows] = np.maximum(result.status[rows], status.numpy())
    # (a failed element's zeros may have been moved along its flat directions)
    return torch.where(torch.from_numpy(is_failure(result.status))[:, None], torch.zeros_like(f), f), result


def _near_least_norm(qp: ConeQP, flats, f: torch.Tensor, first, opts: SolveOptions) -> torch.Tensor:
    """The minimisers f (B, n) of the consistent elements of ``flats`` (a first solve of the batch ``qp``, whose
    result ``first``'s status and residual (B,) are updated in place) that lie farther than ``FAR`` times the size of
    their range part from 0, or whose first solve failed, replaced by a second solve with a curvature
    ``TIKHONOV``·ref on the flat directions.  Returns f.

    Where the set of minimisers is unbounded (a flat direction inside the cones), the first solve can end anywhere
    on it: 2e7 times farther than the least-norm point in a stress problem, accurate relative to that size only, so
    that the move back to the least-norm point left an error of that order (a cone violated by 4 %).  With the
    curvature the minimiser is unique, within a relative O(``TIKHONOV``) of the least-norm one (Tikhonov's), and
    the solver's answer is accurate at its scale; ``least_norm.minimum_norm`` then moves it the rest of the way.
    """
    rows = flats.idx[flats.consistent]
    x = f[rows]
    range_part = x - (flats.PiN[flats.consistent] @ x[..., None])[..., 0]
    status = first.status
    failed = torch.from_numpy(is_failure(status[rows.numpy()]))
    far = torch.zeros_like(flats.consistent)
    far[flats.consistent] = (x.abs().amax(-1) > FAR * range_part.abs().amax(-1)) | failed
    if not far.any():
        return f
    assert qp.lower is not None and qp.active is not None  # (``solve_cone_qp`` made them)
    curvature = TIKHONOV
    while True:
        rows = flats.idx[far]
        A_t = qp.A[rows] + (curvature * flats.ref[far])[:, None, None] * flats.PiN[far]
        curved = ConeQP(A_t, qp.q[rows], qp.mu[rows], qp.lower[rows], qp.active[rows], qp.d)
        again, result = _solve_with_retries(curved, opts.counting())  # (a failure keeps the first answer)
        ok = ~is_failure(result.status)
        rows_ok = rows[torch.from_numpy(ok)].numpy()
        # (a first solve that failed takes this one's status: ill-conditioned along its flat directions, it can
        # fail where the problem with the curvature does not)
        was_failed = is_failure(status[rows_ok])
        status[rows_ok] = np.where(was_failed, result.status[ok], np.maximum(status[rows_ok], result.status[ok]))
        first.residual[rows_ok[was_failed]] = result.residual[ok][was_failed]
        f = f.index_copy(0, torch.from_numpy(rows_ok), again[torch.from_numpy(ok)].to(f.dtype))
        # (where the curved solve failed too, and so the first: once more with a curvature 1000 times larger, up to
        # TIKHONOV_MAX, which keeps the range part to that relative accuracy; minimum_norm then moves the answer)
        still = torch.zeros_like(far)
        still[far] = torch.from_numpy(~ok & is_failure(status[rows.numpy()]))
        curvature *= 1e3
        if not still.any() or curvature > TIKHONOV_MAX:
            return f
        far = still


def _cone_qp(qp: ConeQP, opts: SolveOptions):
    """solve(idx, A, q) → (f, status) of the elements idx of ``qp`` with A (m, n, n), q (m, n) in place of theirs:
    the cone QPs of the least-norm stage (``least_norm.minimum_norm``), differentiable."""
    assert qp.lower is not None and qp.active is not None  # (``solve_cone_qp`` made them)
    mu, lower, active = qp.mu, qp.lower, qp.active

    def solve(idx, A, q):
        f, result = _solve_with_retries(ConeQP(A, q, mu[idx], lower[idx], active[idx], qp.d), opts)
        return f, torch.from_numpy(result.status)

    return solve


def _frictionless_slide_limit(z, A, q, T, gamma, zero_mu, d):
    """For μ = 0 contacts, set the tangential z to its limit as μ → 0⁺: −z_n·ĝ_t; also return ‖g_t‖.

    g_t is the tangential contact velocity A f + q after the impulse and ĝ_t its direction.  The returned f does
    not change (f_t = μ z_t = 0), but the backward pass then gives the one-sided derivative with respect to μ.
    Returns z: (B, n) and the sliding speeds ‖g_t‖: (B, K) (0 where the contact sticks or μ > 0).
    """
    B, n = z.shape
    K = n // d
    f = gamma[:, None] * T * z
    g = (np.matmul(A, f[..., None])[..., 0] + q).reshape(B, K, d)[..., 1:]
    g_norm = np.sqrt((g * g).sum(-1, keepdims=True))
    scale = (np.abs(A.diagonal(axis1=-2, axis2=-1)).max(-1) * np.abs(f).max(-1) + np.abs(q).max(-1))[:, None, None]
    sliding = (g_norm > 1e-9 * np.maximum(scale, 1e-300)) & zero_mu[..., None]
    zk = z.reshape(B, K, d)
    zt = np.where(sliding, -zk[..., :1] * g / np.maximum(g_norm, 1e-300), zk[..., 1:])
    speed = np.where(sliding[..., 0], g_norm[..., 0], 0.0)
    return np.ascontiguousarray(np.concatenate([zk[..., :1], zt], -1).reshape(B, n)), speed


def _solve_passes(A, T, c, l_hat, on_q, on_l, d, idx, passes, options, start_margin, out) -> None:
    """Solve the elements ``idx`` into ``out``, pass after pass of ``passes`` (their tolerances), each pass only on
    the elements the previous left INACCURATE or MAX_ITER.  Where a pass again ends INACCURATE or MAX_ITER with a
    higher residual than the previous pass's answer, that answer is kept: CONVERGED if it meets this pass's
    criterion (residual ≤ ``final_tol``), else if usable, as INACCURATE (a stalled pass-1 answer is not kept: on an
    unbounded problem it would set the scale of the retries).  On a problem with a face
    of minimisers (a box resting on four corners: A of rank 6 in 12 contact rows) the method run to a tight
    tolerance can stall at a residual 500 times above the one polishing reached from pass 1's looser start.  (An
    unbounded verdict stays as this pass leaves it, for the retries.)"""
    kept = None
    for tols in passes:
        kernel.solve(A, T, c, l_hat, on_q, on_l, d, idx, **tols, **options, start_margin=start_margin, out=out)
        if kept is not None:
            now = out.status[idx]
            kept_res = kept["residual"]
            stalled = ((now == _INACCURATE) | (now == _MAX_ITER)) & (kept_res < out.residual[idx])
            better = stalled | (now == _NUMERICAL)
            better &= (kept_res <= tols["final_tol"]) | (kept["status"] == _INACCURATE)
            if better.any():
                rows = idx[better]
                for name in kernel.IPMResult.OUTPUTS:
                    getattr(out, name)[rows] = kept[name][better]
                met = rows[kept_res[better] <= tols["final_tol"]]
                out.status[met] = _CONVERGED
        status = out.status if len(idx) == len(out.status) else out.status[idx]  # (idx is all of them, or sorted)
        if not np.count_nonzero(status):
            break
        idx = idx[(status == _INACCURATE) | (status == _MAX_ITER)]
        if not len(idx):
            break
        kept = {name: getattr(out, name)[idx] for name in kernel.IPMResult.OUTPUTS}  # (copies: fancy indexing)
