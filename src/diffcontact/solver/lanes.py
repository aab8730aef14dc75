"""The interior-point method's compiled kernel (``lanes/ipm_lanes.hpp``): W problems at a time in SIMD lanes.

Built with the package (``setup.py``) and called through ctypes, which releases the GIL, so the batch is split
among threads here.  The lane width (8 with AVX-512, 4 with AVX2, else 2) is chosen from the CPU at run time;
the environment variable ``DIFFCONTACT_LANES`` (8, 4 or 2) forces one that the CPU supports.
"""

from __future__ import annotations

import ctypes
import os
from concurrent.futures import ThreadPoolExecutor

import numba

from diffcontact.solver import _lanes

_lib = ctypes.CDLL(_lanes.__file__)
_lib.diffcontact_ipm_supported.restype = ctypes.c_int
_lib.diffcontact_ipm_select.restype = ctypes.c_int
_lib.diffcontact_ipm_select.argtypes = [ctypes.c_int]
_lib.diffcontact_ipm_width.restype = ctypes.c_int
_solve = _lib.diffcontact_ipm_solve
_solve.restype = ctypes.c_int
_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
_solve.argtypes = [_P] * 5 + [_I, _I, _P, _I, _D, _D, _I, _D, _D] + [_P] * 9 + [_I]


def supported_widths() -> list[int]:
    """Lane widths this CPU can run, widest first."""
    bits = _lib.diffcontact_ipm_supported()
    return [w for w in (8, 4, 2) if bits & w]


def select_width(width: int | None = None) -> int:
    """Use the kernel of this lane width (None: the widest this CPU runs, or ``DIFFCONTACT_LANES``); returns it."""
    if width is None:
        env = os.environ.get("DIFFCONTACT_LANES")
        width = int(env) if env else supported_widths()[0]
    if width not in (8, 4, 2) or not _lib.diffcontact_ipm_select(width):
        raise ValueError(f"lane width {width} is not available on this CPU: choose one of {supported_widths()}")
    return width


select_width()

_pool: ThreadPoolExecutor | None = None


def solve(P, c, low, on, onl, d: int, idx, *, tol, acc_tol, max_iter, margin, refine_tol, out, trace) -> None:
    """Run the interior-point method on the batch elements ``idx`` (int64) in place of ``out``.

    P: (B, n, n), c: (B, n), low: (B, K) float64; on, onl: (B, K) bool (C-contiguous); out: the tuple
    (z (B, n), s_l, lam_l (B, K), s_q, lam_q (B, K, d), status, iterations (B,) int64, residual (B,)) written
    at the rows ``idx``; trace: (B, T, 4) (T may be 0).  Elements are split among ``numba.get_num_threads()``
    threads in runs of whole lane groups.
    """
    global _pool
    K = low.shape[1]
    ptr = [a.ctypes.data for a in (P, c, low, on, onl)]
    optr = [a.ctypes.data for a in out] + [trace.ctypes.data]

    def run(part):
        rc = _solve(
            *ptr, K, d, part.ctypes.data, len(part), tol, acc_tol, max_iter, margin, refine_tol, *optr, trace.shape[1]
        )
        if rc != 0:
            raise MemoryError(f"interior-point kernel: out of memory for K = {K} (code {rc})")

    width = _lib.diffcontact_ipm_width()
    threads = min(numba.get_num_threads(), len(idx) // (2 * width))
    if threads <= 1:
        run(idx)
        return
    if _pool is None or _pool._max_workers < threads:
        _pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="diffcontact-ipm")
    groups = -(-len(idx) // width)
    bounds = [width * (groups * t // threads) for t in range(threads + 1)]
    parts = [idx[bounds[t] : min(bounds[t + 1], len(idx))] for t in range(threads)]
    for f in [_pool.submit(run, p) for p in parts]:
        f.result()
