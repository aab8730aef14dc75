"""The solver's compiled kernel (``csrc/``, interface ``csrc/api.h``): a batched primal-dual interior-point method
for many small contact cone QPs, W problems at a time in the lanes of SIMD vectors (no autograd).

Standard form, per batch element (all contacts of dimension d, K contacts, n = K·d variables):

    minimise ½ zᵀPz + cᵀz   subject to   z_n,i ≥ l_i  and  ‖z_t,i‖ ≤ z_n,i   for every active contact i,

i.e. G z + s = h with s in the product of K non-negative rays and (if d ≥ 2) K second-order cones, where
G z = (−z_n,i ; −z_i) and h = (−l_i ; 0).  Inactive contacts have no cones and P = I, c = 0 there, so z = 0.

The method is Mehrotra's predictor–corrector with Nesterov–Todd scaling (as in CVXOPT's coneqp,
``csrc/ipm_lanes.hpp``).  The reduced Newton matrix H = P + GᵀW⁻²G is P plus a d×d block per contact; it is
positive definite even when P is singular, and one Cholesky factor serves both directions of an iteration.  Newton
steps on the exact optimality conditions then polish the solution to rounding accuracy (``csrc/exact_lanes.hpp``,
equations in ``kkt.py``).  The tolerances and the retries are the caller's (``problem._solve_with_retries``).

Three entry points: the interior-point method followed by polishing (``solve``), the adjoint solve of the
backward pass (``adjoint``) and the Cholesky test for flat directions of the input (``flat_test``, for
``flat.flat_elements``).  Built with the package (``setup.py``) as the extension module ``_lanes``, whose
functions release the GIL while the kernel runs, so the batch is split among threads here.  The lane width (8 with
AVX-512, 4 with AVX2, else 2) is chosen from the CPU on first use; the environment variable ``DIFFCONTACT_LANES``
(8, 4 or 2) forces one that the CPU supports.
"""

from __future__ import annotations

import functools
import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import overload

import numba
import numpy as np

from diffcontact.solver.status import FIRST_FAILURE, WEAK_TOL, Status

API_VERSION = 6


def _load():
    """The kernel's extension module (``_lanes``, built by ``setup.py``), checked against the Python copies of the
    facts of ``csrc/api.h``."""
    build = "build it with `pip install -e .` or `python setup.py build_ext --inplace`"
    try:
        from diffcontact.solver import _lanes
    except ImportError as e:  # (missing, or a build from before it was a module: no PyInit__lanes)
        raise ImportError(f"the contact solver's compiled kernel cannot be loaded ({e}): {build}") from e
    got = _lanes.constants()
    want = {
        "api_version": API_VERSION,
        **{status.name.lower(): int(status) for status in Status},
        "first_failure": int(FIRST_FAILURE),
        "weak_tol": WEAK_TOL,
    }
    if got != want:
        stale = f"{_lanes.__file__} disagrees with kernel.py (a stale build?)"
        raise ImportError(f"{stale}: kernel {got}, Python {want}; {build}")
    return _lanes


_lib = _load()
_width: int | None = None  # chosen on first use (a bad DIFFCONTACT_LANES must not break the import)


def supported_widths() -> list[int]:
    """Lane widths this CPU can run, widest first."""
    bits = _lib.supported()
    return [w for w in (8, 4, 2) if bits & w]


def select_width(width: int | None = None) -> int:
    """Use the kernel of this lane width (None: ``DIFFCONTACT_LANES`` if set, else the widest this CPU runs);
    returns it."""
    global _width, _inline_below
    source = f"lane width {width}"
    if width is None:
        env = os.environ.get("DIFFCONTACT_LANES", "")
        source = f"DIFFCONTACT_LANES={env!r}"
        width = int(env) if env.strip().isdigit() else (supported_widths()[0] if not env else -1)
    if width not in (8, 4, 2) or not _lib.select(width):
        raise ValueError(f"{source}: not a lane width this CPU runs; choose one of {supported_widths()}")
    _width, _inline_below = width, 0
    return width


def current_width() -> int:
    """The lane width in use (chosen by ``select_width()`` on first use)."""
    return _width if _width is not None else select_width()


_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_numba_started = False
_inline_below = 0  # batches smaller than this run in the calling thread (set by the first call of ``parallel``)


def parallel(run, count: int) -> None:
    """Call run(start, stop) on contiguous runs of whole lane groups of range(count), one per thread.

    The solver's threads (``numba.get_num_threads()`` of them): the calling thread and a pool of Python threads
    that wait on a lock when idle, running code that releases the GIL (this kernel, numba functions compiled with
    ``nogil``).  One pool for every stage: OpenMP workers of a ``prange`` would spin after their loop and compete
    with it for the cores.
    """
    global _pool, _pool_size, _numba_started, _inline_below
    if count < _inline_below:  # (one thread: the common small call, without the questions below)
        run(0, count)
        return
    width = current_width()
    if not _numba_started:
        # numba starts its threading layer on the first query, which can change the state of the OpenMP runtime
        # that torch shares: start it on the first call, whatever the batch, so that a process's floating-point
        # results do not depend on the sizes of its first batches
        numba.get_num_threads()
        _numba_started = True
        _inline_below = 4 * width
    # (one thread below 4 groups, without asking numba: its query costs µs, a problem of a simulation step ~10 µs)
    threads = min(numba.get_num_threads(), count // (2 * width)) if count >= 4 * width else 1
    if threads <= 1:
        run(0, count)
        return
    if _pool is None or _pool_size < threads - 1:
        _pool = ThreadPoolExecutor(max_workers=threads - 1, thread_name_prefix="diffcontact-solver")
        _pool_size = threads - 1
    groups = -(-count // width)
    bounds = [min(count, width * (groups * t // threads)) for t in range(threads + 1)]
    # the last run in the calling thread (each hand-over to a waiting thread and back costs tens of µs)
    futures = [_pool.submit(run, bounds[t], bounds[t + 1]) for t in range(threads - 1)]
    try:
        run(bounds[-2], bounds[-1])
    finally:
        for f in futures:
            f.result()


class _Output:
    """An output of ``IPMResult``: a view of its buffer, made on first access and then kept as an instance attribute
    (a call without gradients reads only z and status; eight views made up front cost 3 µs of a small call)."""

    def __init__(self, i: int, dtype: type[np.generic] = np.float64):
        self.i, self.dtype = i, dtype

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    @overload
    def __get__(self, obj: None, objtype: type | None = None) -> _Output: ...
    @overload
    def __get__(self, obj: IPMResult, objtype: type | None = None) -> np.ndarray: ...
    def __get__(self, obj: IPMResult | None, objtype: type | None = None) -> _Output | np.ndarray:
        if obj is None:
            return self
        a, b, shape = obj._slices[self.i]
        view = obj._buffer[a:b].reshape(shape)
        view = view if self.dtype is np.float64 else view.view(self.dtype)
        obj.__dict__[self.name] = view  # (shadows this non-data descriptor from now on)
        return view


class IPMResult:
    """What ``solve`` returns: the solution, its status, and what the backward pass needs (float64 numpy, C-contiguous;
    B batch, K contacts, n = K·d).  Rows not solved keep their initial values (z = 0, unit ray slacks and
    multipliers, status CONVERGED).  The outputs are views of one buffer (``_layout``), which the kernel writes."""

    z = _Output(0)  # (B, n)
    s_l = _Output(1)  # (B, K) slack and multiplier of the rays
    lam_l = _Output(2)
    s_q = _Output(3)  # (B, K, d) slack and multiplier of the second-order cones
    lam_q = _Output(4)
    status = _Output(5, np.int64)  # (B,) int64 ``Status`` codes
    iterations = _Output(6, np.int64)  # (B,) int64 interior-point iterations
    residual = _Output(7)  # (B,) scaled KKT residual of the returned point

    OUTPUTS = ("z", "s_l", "lam_l", "s_q", "lam_q", "status", "iterations", "residual")  # (csrc/lanes_module.cpp)

    def __init__(self, A: np.ndarray, T: np.ndarray, on: np.ndarray, on_l: np.ndarray, d: int):
        """Outputs in their initial state for the problems P = T·A·T (A: (B, n, n) symmetric, T: (B, n); see
        ``solve``; the problem's data, for the backward pass), on (B, K) bool (cones in use) and on_l (B, K) bool
        (rays in use), of contact dimension d."""
        B, K = on.shape
        self.A, self.T, self.on, self.on_l, self.d = A, T, on, on_l, d
        self._slices, initial = _layout(B, K, d)
        self._buffer = initial.copy()  # (8-byte items: the int64 outputs are views of it too)

    def __repr__(self) -> str:
        B, n = self.z.shape
        return f"IPMResult(B={B}, n={n}, status={self.status!r})"


@functools.lru_cache(maxsize=64)
def _layout(B: int, K: int, d: int) -> tuple[tuple, np.ndarray]:
    """The layout of an ``IPMResult``'s buffer: (start, stop, shape) of each output in ``IPMResult.OUTPUTS``
    order (the kernel's, ``outputs`` in ``csrc/lanes_module.cpp``, which checks the buffer's size), and the buffer's
    initial content (read-only: zeros, and unit ray slacks and multipliers)."""
    slices, end = [], 0
    for shape in ((B, K * d), (B, K), (B, K), (B, K, d), (B, K, d), (B,), (B,), (B,)):
        start, end = end, end + math.prod(shape)
        slices.append((start, end, shape))
    initial = np.zeros(end)
    initial[slices[1][0] : slices[2][1]] = 1.0
    initial.flags.writeable = False
    return tuple(slices), initial


_NO_TRACE = np.zeros((0, 0, 4))


def solve(
    A: np.ndarray,
    T: np.ndarray,
    c: np.ndarray,
    lower: np.ndarray,
    on: np.ndarray,
    on_l: np.ndarray,
    d: int,
    idx: np.ndarray | None = None,
    *,
    ipm_tol: float,
    final_tol: float,
    acceptable_tol: float,
    max_iter: int,
    start_margin: float,
    refine_tol: float,
    polish_steps: int,
    out: IPMResult | None = None,
    trace: np.ndarray | None = None,
) -> IPMResult:
    """Interior-point method to ``ipm_tol``, then (``polish_steps`` > 0) polishing, of the batch elements ``idx``
    (default: all); the options are the fields of ``SolveArgs`` (``csrc/api.h``), under the same names.

    The problems' P = T·A·T is formed in the kernel (``scaled_matrix``): A (B, n, n) symmetric, T (B, n); c: (B, n),
    lower: (B, K) float64; on, on_l: (B, K) bool; idx: (m,) int64 (all C-contiguous).  A problem written with P
    itself is solved with A = P and T = 1.
    Writes the rows ``idx`` of ``out`` (default: a new ``IPMResult``) and returns it.  ``trace`` (B, T, 4),
    if given, receives per iteration the primal and dual residuals, the gap and the step taken (for diagnosis).
    """
    B, K = lower.shape
    out = IPMResult(A, T, on, on_l, d) if out is None else out
    idx = np.arange(B, dtype=np.int64) if idx is None else idx
    if trace is None:
        trace = _NO_TRACE
    elif trace.dtype != np.float64 or trace.ndim != 3 or trace.shape[::2] != (B, 4) or not trace.flags.c_contiguous:
        raise ValueError(f"trace must be a C-contiguous float64 array of shape (B, T, 4) with B = {B}")
    buffer, solve_ = out._buffer, _lib.solve
    options = (K, d, ipm_tol, final_tol, acceptable_tol, max_iter, start_margin, refine_tol, polish_steps)
    parallel(lambda start, stop: solve_(A, T, c, lower, on, on_l, idx, trace, buffer, *options, start, stop), len(idx))
    return out


def adjoint(res: IPMResult, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve Kᵀ[u; v] = [g; 0] per element at the solution ``res`` (``implicit.py``), the weakly active cones of
    singular elements taken as inactive.  g: (B, n) float64, C-contiguous.  Returns u: (B, n), the rays' v: (B, K)
    and ok: (B,) bool (False where K is singular even so)."""
    B, K = res.on.shape
    n = K * res.d
    u, v_l = np.empty((B, n)), np.empty((B, K))
    ok = np.empty(B, dtype=np.bool_)
    args = (res.A, res.T, res._buffer, res.on, res.on_l, g, u, v_l, ok, K, res.d)
    parallel(lambda start, stop: _lib.adjoint(*args, start, stop), B)
    return u, v_l, ok


def flat_test(
    A: np.ndarray, mu: np.ndarray, active: np.ndarray, d: int, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B,) bool: where ½(A + Aᵀ) − tol·ref·I on the rows in use is not positive definite (``FlatArgs`` of
    ``csrc/api.h``; ``flat.flat_elements``); read in the same pass, (B,) bool: where every entry of A is finite, and
    (B,) bool: where A equals its transpose exactly.  A: (B, n, n), mu: (B, K) float64; active: (B, K) bool
    (C-contiguous)."""
    B, K = mu.shape
    flags = np.zeros((3, B), dtype=np.bool_)
    parallel(lambda start, stop: _lib.flat(A, mu, active, flags, K, d, tol, start, stop), B)
    return flags[0], flags[1], flags[2]


@numba.njit(cache=True, nogil=True)
def scaled_matrix(A: np.ndarray, T: np.ndarray) -> np.ndarray:
    """P = T·A·T (B, n, n) of A (B, n, n) and T (B, n), with 1 on the diagonal where T_i = 0 (a row the answer does
    not depend on: an inactive contact, the tangential rows of a μ = 0 contact), as the kernel forms it."""
    B, n = T.shape
    P = np.empty((B, n, n))
    for b in range(B):
        for i in range(n):
            for j in range(n):
                P[b, i, j] = T[b, i] * A[b, i, j] * T[b, j]
            if T[b, i] == 0.0:
                P[b, i, i] += 1.0
    return P
