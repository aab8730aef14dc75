"""The cost of importing torch before diffcontact: python investigations/import_order.py [K d B rounds].

Imported first, diffcontact sets ``OMP_WAIT_POLICY=PASSIVE`` before torch loads its OpenMP runtime; imported after
torch, it is too late (the runtime read the variable when it loaded) and torch's workers spin after each of its
parallel regions, beside the solver's threads (``diffcontact.threads.spin_warning``).  This script times forward +
backward of ``solve_cone_qp`` on the instances of ``diffcontact bench solver`` as that benchmark times them (2
threads, median of 10 calls after 2) in fresh processes that import in either order, alternating, and prints µs
per problem for each order.
"""

from __future__ import annotations

import os
import subprocess
import sys

CHILD = """
import {first}
import {second}
from diffcontact.bench.solver import _instances, _time_fwd_bwd
from diffcontact.solver import solve_cone_qp
from diffcontact.threads import set_threads
set_threads(2)
A, q, mu, lower = _instances(torch.Generator().manual_seed(0), {B}, {K}, {d})
solve_cone_qp(A, q, mu, lower)  # (a second warm-up call before _time_fwd_bwd's own)
print(1e6 * _time_fwd_bwd(solve_cone_qp, A, q, mu, lower, 10)[0] / {B})
"""


def main(K: int = 19, d: int = 3, B: int = 800, rounds: int = 3) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "KMP_BLOCKTIME", "OMP_NUM_THREADS")}
    orders = {"diffcontact first": ("diffcontact", "torch"), "torch first": ("torch", "diffcontact")}
    results: dict[str, list[float]] = {name: [] for name in orders}
    for _ in range(rounds):
        for name, (first, second) in orders.items():
            code = CHILD.format(first=first, second=second, K=K, d=d, B=B)
            out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            results[name].append(float(out.stdout.split()[-1]))
    print(f"K = {K}, d = {d}, B = {B}, 2 threads, forward + backward, µs per problem ({rounds} processes each):")
    for name, values in results.items():
        print(f"  {name}: {min(values):.1f}-{max(values):.1f}")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:5]))
