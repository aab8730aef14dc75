"""The solver's fixed cost per call at B = 1: python benchmarks/bench_solver_call.py [d K].

Prints the fastest of 300 single calls (after 50 warm-up calls) of the forward pass without gradients (as in a
simulation step) and of forward + backward; one torch thread.  On a shared machine compare two checkouts by
alternating runs of this script (docs/solver.md, "Speed").
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import sys
import time

import torch

from diffcontact.solver import solve_cone_qp


def _fastest(call, runs: int = 300, warm_up: int = 50) -> float:
    for _ in range(warm_up):
        call()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(d: int = 3, K: int = 1) -> None:
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(0)
    n = K * d
    M = torch.randn(1, n, n, generator=gen, dtype=torch.float64)
    A = M @ M.mT / n + 0.1 * torch.eye(n, dtype=torch.float64)
    q = torch.randn(1, n, generator=gen, dtype=torch.float64)
    mu = torch.rand(1, K, generator=gen, dtype=torch.float64)
    lower = 0.3 * torch.rand(1, K, generator=gen, dtype=torch.float64)

    def forward():
        with torch.no_grad():
            solve_cone_qp(A, q, mu, lower)

    def forward_backward():
        inputs = [t.clone().requires_grad_() for t in (A, q, mu, lower)]
        solve_cone_qp(*inputs).sum().backward()

    print(
        f"d = {d}, K = {K}, B = 1: forward without gradients {1e6 * _fastest(forward):.1f} µs, "
        f"forward + backward {1e6 * _fastest(forward_backward):.1f} µs (fastest of 300 calls)"
    )


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
