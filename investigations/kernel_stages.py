"""The compiled kernel's stages per problem: python investigations/kernel_stages.py [K d B].

CPU µs per problem (best of 5, one thread) of the interior-point method alone (``kernel.solve`` without polishing),
of polishing (with it, minus without), of the adjoint solve of the backward pass (``kernel.adjoint``) and of the
flat-direction test (``least_norm.flat_elements``), on the scaled instances of ``diffcontact bench solver``.  On a
shared machine compare two checkouts by alternating runs of this script (docs/solver.md, "Speed").
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import sys
import time

import numpy as np
import torch

from diffcontact.bench.solver import _instances
from diffcontact.solver import kernel, least_norm, problem, scaling
from diffcontact.solver.kkt import contact_dims


def _best(call, B: int, runs: int = 5) -> float:
    times = []
    for _ in range(runs):
        t0 = time.process_time()
        call()
        times.append(time.process_time() - t0)
    return 1e6 * min(times) / B


def main(K: int = 19, d: int = 3, B: int = 400) -> None:
    A, q, mu, lower = _instances(torch.Generator().manual_seed(0), B, K, d)
    arrays = problem._as_arrays(A, q, mu, lower, None)
    A_sym, c, l_hat, T, on_q, on_l = (scaling.scale_batch(*arrays, contact_dims(d))[i] for i in (0, 1, 2, 3, 8, 9))
    options = dict(
        ipm_tol=problem.IPM_TOL,
        final_tol=problem.ROUNDING_TOL,
        acceptable_tol=1e-7,
        max_iter=60,
        refine_tol=problem.IPM_TOL,
        start_margin=problem.START_MARGIN,
    )

    def solve(steps: int):
        return kernel.solve(A_sym, T, c, l_hat, on_q, on_l, d, **options, polish_steps=steps)

    ipm = _best(lambda: solve(0), B)
    polish = _best(lambda: solve(problem.POLISH_STEPS), B) - ipm
    res = solve(problem.POLISH_STEPS)
    g = np.random.default_rng(0).standard_normal(res.z.shape)
    adjoint = _best(lambda: kernel.adjoint(res, g), B)
    flat_test = _best(lambda: least_norm.flat_elements(arrays[0], arrays[2], arrays[4], d, 1e-6), B)
    print(
        f"K = {K}, d = {d}, B = {B}, {kernel.current_width()} lanes: CPU µs per problem: interior-point method "
        f"{ipm:.1f}, polishing {polish:.1f}, adjoint solve {adjoint:.1f}, flat-direction test {flat_test:.1f} "
        f"(iterations: mean {res.iterations.mean():.2f})"
    )


if __name__ == "__main__":
    torch.set_num_threads(1)
    main(*(int(a) for a in sys.argv[1:4]))
