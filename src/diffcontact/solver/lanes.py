"""The solver's compiled kernel (``csrc/*.hpp``): W problems at a time in the lanes of SIMD vectors.

Two entry points: the interior-point method followed by polishing (``solve``), and the adjoint solve of the
backward pass (``adjoint``).

Built with the package (``setup.py``) and called through ctypes, which releases the GIL, so the batch is split
among threads here.  The lane width (8 with AVX-512, 4 with AVX2, else 2) is chosen from the CPU at run time;
the environment variable ``DIFFCONTACT_LANES`` (8, 4 or 2) forces one that the CPU supports.
"""

from __future__ import annotations

import ctypes
import os
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from diffcontact.solver import _lanes

_lib = ctypes.CDLL(_lanes.__file__)
_lib.diffcontact_ipm_supported.restype = ctypes.c_int
_lib.diffcontact_ipm_select.restype = ctypes.c_int
_lib.diffcontact_ipm_select.argtypes = [ctypes.c_int]
_lib.diffcontact_ipm_width.restype = ctypes.c_int
_solve = _lib.diffcontact_ipm_solve
_solve.restype = ctypes.c_int
_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
_solve.argtypes = [_P] * 5 + [_I, _I, _P, _I, _D, _D, _D, _I, _D, _D, _I, _I] + [_P] * 10 + [_I]
_adjoint = _lib.diffcontact_adjoint_solve
_adjoint.restype = ctypes.c_int
_adjoint.argtypes = [_P] * 7 + [_I, _I, _P, _I, _I, _P, _P, _P]


def supported_widths() -> list[int]:
    """Lane widths this CPU can run, widest first."""
    bits = _lib.diffcontact_ipm_supported()
    return [w for w in (8, 4, 2) if bits & w]


def select_width(width: int | None = None) -> int:
    """Use the kernel of this lane width (None: ``DIFFCONTACT_LANES`` if set, else the widest this CPU runs);
    returns it."""
    source = f"lane width {width}"
    if width is None:
        env = os.environ.get("DIFFCONTACT_LANES", "")
        source = f"DIFFCONTACT_LANES={env!r}"
        width = int(env) if env.strip().isdigit() else (supported_widths()[0] if not env else -1)
    if width not in (8, 4, 2) or not _lib.diffcontact_ipm_select(width):
        raise ValueError(f"{source}: not a lane width this CPU runs; choose one of {supported_widths()}")
    return width


def current_width() -> int:
    """The lane width in use."""
    return _lib.diffcontact_ipm_width()


select_width()

_pool: ThreadPoolExecutor | None = None
_pool_size = 0


def parallel(run, count: int) -> None:
    """Call run(start, stop) on contiguous runs of whole lane groups of range(count), one per thread.

    The solver's threads (``numba.get_num_threads()`` of them): Python threads that wait on a lock when idle,
    running code that releases the GIL (this kernel, numba functions compiled with ``nogil``).  One pool for
    every stage: OpenMP workers of a ``prange`` would spin after their loop and compete with it for the cores.
    """
    global _pool, _pool_size
    width = current_width()
    threads = min(numba.get_num_threads(), count // (2 * width))
    if threads <= 1:
        run(0, count)
        return
    if _pool is None or _pool_size < threads:
        _pool, _pool_size = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="diffcontact-solver"), threads
    groups = -(-count // width)
    bounds = [min(count, width * (groups * t // threads)) for t in range(threads + 1)]
    for f in [_pool.submit(run, bounds[t], bounds[t + 1]) for t in range(threads)]:
        f.result()


def _check(rc: int, K: int) -> None:
    if rc == -1:
        raise MemoryError(f"contact solver kernel: out of memory for K = {K}")
    if rc != 0:
        raise RuntimeError(f"contact solver kernel failed (code {rc})")


def solve(
    P,
    c,
    low,
    on,
    onl,
    d: int,
    idx,
    *,
    tol_ipm,
    tol,
    acc_tol,
    max_iter,
    margin,
    refine_tol,
    polish_steps,
    last,
    out,
    again,
    trace,
) -> None:
    """Interior-point method to ``tol_ipm``, then (``polish_steps`` > 0) polishing, of the batch elements ``idx``.

    P: (B, n, n), c: (B, n), low: (B, K) float64; on, onl: (B, K) bool; idx: (m,) int64 (all C-contiguous);
    out: the tuple (z (B, n), s_l, lam_l (B, K), s_q, lam_q (B, K, d), status, iterations (B,) int64, residual
    (B,)) written at the rows ``idx``; again: (B,) bool, set where an element did not converge to rounding level
    and ``last`` is False (see ``ipm.solve_ipm``); trace: (B, T, 4) (T may be 0).
    """
    K = low.shape[1]
    ptr = [a.ctypes.data for a in (P, c, low, on, onl)]
    optr = [a.ctypes.data for a in out] + [again.ctypes.data, trace.ctypes.data]
    opts = (tol_ipm, tol, acc_tol, max_iter, margin, refine_tol, polish_steps, int(last))

    def run(start, stop):
        part = idx[start:stop]
        _check(_solve(*ptr, K, d, part.ctypes.data, len(part), *opts, *optr, trace.shape[1]), K)

    parallel(run, len(idx))


def adjoint(P, s_l, lam_l, s_q, lam_q, on, onl, d: int, g):
    """Solve Kᵀ[u; v] = [g; 0] per element (``implicit.py``), the weakly active cones of singular elements taken
    as inactive.  Arrays as in ``solve`` (C-contiguous), g: (B, n).  Returns u: (B, n), the rays' v: (B, K) and
    ok: (B,) bool (False where K is singular even so)."""
    B, K = s_l.shape
    u = np.empty((B, K * d))
    v_l = np.empty((B, K))
    ok = np.empty(B, dtype=np.bool_)
    ptr = [a.ctypes.data for a in (P, s_l, lam_l, s_q, lam_q, on, onl)]

    def run(start, stop):
        _check(_adjoint(*ptr, K, d, g.ctypes.data, start, stop, u.ctypes.data, v_l.ctypes.data, ok.ctypes.data), K)

    parallel(run, B)
    return u, v_l, ok
