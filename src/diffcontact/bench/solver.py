"""Solver benchmark: forward+backward time per problem, ours against the cvxpylayers reference, in one run."""

from __future__ import annotations

import platform
import statistics
import time

import torch

import diffcontact
from diffcontact.bench import check_counts
from diffcontact.errors import ConfigError
from diffcontact.solver import solve_cone_qp

REFERENCE_EPS = 1e-8  # SCS tolerance of the cvxpylayers baseline


def _instances(gen: torch.Generator, B: int, K: int, d: int):
    n = K * d
    M = torch.randn(B, n, n, generator=gen, dtype=torch.float64)
    A = M @ M.mT / n + 0.1 * torch.eye(n, dtype=torch.float64)
    q = torch.randn(B, n, generator=gen, dtype=torch.float64)
    mu = torch.rand(B, K, generator=gen, dtype=torch.float64)
    lower = 0.3 * torch.rand(B, K, generator=gen, dtype=torch.float64)
    return A, q, mu, lower


def _time_fwd_bwd(solver, A, q, mu, lower, repeats: int) -> tuple[float, float, torch.Tensor]:
    """(median wall-clock time, median CPU time of the process (all its threads), f) of forward + backward."""
    times, cpu_times, f = [], [], None
    for _ in range(repeats + 1):  # the first run is warm-up
        ins = [t.clone().requires_grad_() for t in (A, q, mu, lower)]
        t0, c0 = time.perf_counter(), time.process_time()
        f = solver(*ins)
        f.sum().backward()
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.process_time() - c0)
    if f is None:
        raise ValueError(f"repeats = {repeats} is not >= 0")
    return statistics.median(times[1:]), statistics.median(cpu_times[1:]), f.detach()


def run_solver_benchmark(
    batches=(1, 128, 800),
    contacts=(1, 2, 3, 5, 19),
    dims=(1, 2, 3),
    repeats: int = 7,
    reference: bool = True,
    ref_max_batch: int = 64,
    seed: int = 0,
    out: str | None = None,
) -> list[dict]:
    """Print (and optionally write as Markdown) the table; returns its rows."""
    check_counts(batches=batches, contacts=contacts, repeats=repeats, ref_max_batch=ref_max_batch)
    if not dims or any(d not in (1, 2, 3) for d in dims):
        raise ConfigError(f"dims = {dims!r}: every contact dimension must be 1, 2 or 3")
    # (threads: the caller's, e.g. `diffcontact bench solver --threads N`)
    reference_solver = None  # (with ``reference``)
    if reference:
        import functools

        from diffcontact.solver.reference import solve_cone_qp_reference

        reference_solver = functools.partial(solve_cone_qp_reference, eps=REFERENCE_EPS)
    print(
        f"diffcontact {diffcontact.__version__}, torch {torch.__version__}, {platform.machine()}, "
        f"{torch.get_num_threads()} threads; medians of {repeats} runs (reference: 3) after one warm-up; "
        "forward+backward; "
        f"reference: cvxpylayers/diffcp/SCS eps {REFERENCE_EPS:g}"
    )
    # (CPU time, of all the process's threads: the work done, less affected than wall-clock time by other
    # processes on a shared machine)
    header = (
        "| d | K | B | ours µs/problem | reference µs/problem | speed-up | ours CPU µs | reference CPU µs | "
        "CPU speed-up | max abs diff | max diff / max(1, ‖f‖∞) |"
    )
    lines = [header, "|---|---|---|---|---|---|---|---|---|---|---|"]
    print(header)
    rows = []
    gen = torch.Generator().manual_seed(seed)
    for d in dims:
        for K in contacts:
            for B in batches:
                A, q, mu, lower = _instances(gen, B, K, d)
                t_ours, c_ours, f_ours = _time_fwd_bwd(solve_cone_qp, A, q, mu, lower, repeats)
                row = {"d": d, "K": K, "B": B, "ours_us": 1e6 * t_ours / B, "ours_cpu_us": 1e6 * c_ours / B}
                if reference_solver is not None:
                    Br = min(B, ref_max_batch)
                    # (its cost varies by ±30 % from run to run on a shared machine: a median of 3)
                    ref_in = (A[:Br], q[:Br], mu[:Br], lower[:Br])
                    t_ref, c_ref, f_ref = _time_fwd_bwd(reference_solver, *ref_in, repeats=3)
                    row["ref_us"], row["ref_cpu_us"] = 1e6 * t_ref / Br, 1e6 * c_ref / Br
                    row["speedup"] = row["ref_us"] / row["ours_us"]
                    row["cpu_speedup"] = row["ref_cpu_us"] / row["ours_cpu_us"]
                    err = (f_ours[:Br] - f_ref).abs().amax(-1)
                    row["diff"] = float(err.max())
                    # relative to the size of each problem's solution, at least 1 (the reference's own error scales
                    # with it)
                    row["rel_diff"] = float((err / f_ref.abs().amax(-1).clamp_min(1.0)).max())
                rows.append(row)
                nan = float("nan")
                line = (
                    f"| {d} | {K} | {B} | {row['ours_us']:.1f} | {row.get('ref_us', nan):.1f} | "
                    f"{row.get('speedup', nan):.0f}× | {row['ours_cpu_us']:.1f} | {row.get('ref_cpu_us', nan):.1f} | "
                    f"{row.get('cpu_speedup', nan):.0f}× | {row.get('diff', nan):.1e} | "
                    f"{row.get('rel_diff', nan):.1e} |"
                )
                print(line, flush=True)
                lines.append(line)
    if out:
        from diffcontact.files import write_text

        write_text(out, "\n".join(lines) + "\n")
    return rows
