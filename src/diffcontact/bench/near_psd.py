"""Stress test of the contact solver on effective-mass matrices that are PSD only up to rounding (solver/least_norm.py):
singular PSD A of every contact dimension and size the 8 benchmark tasks use, formed in float32 (their null directions
get eigenvalues of ± the rounding of their rows), with q in the range of A (as J v for a velocity that obeys the
joints)."""

from __future__ import annotations

import time

import torch

from diffcontact.bench import check_counts
from diffcontact.solver import Status, solve_cone_qp

# (K, d): rope (d = 1, up to 19 contacts), balls / pendulum / disks (d = 2, up to 5), gyroscope (d = 3)
TASK_SIZES = [(1, 1), (3, 1), (19, 1), (1, 2), (2, 2), (5, 2), (1, 3), (2, 3)]


def near_psd_instance(gen: torch.Generator, B: int, K: int, d: int, mu_scale: float = 1.5):
    """B random problems: A = F Fᵀ of rank r = n − 1 − (0 … n/3), formed in float32 as a simulator forms the effective
    mass Z Zᵀ (its rounding relative to A's rows: a null direction's eigenvalue becomes ±eps·its rows' scale); q =
    F w; μ uniform in [0, mu_scale); a lower bound 0 … 0.3 on 30 % of the contacts.

    Returns (A, q, mu, lower) in float32 and (F, w) in float64 (A ≈ F Fᵀ, q = F w).
    """
    n = K * d
    r = max(1, n - 1 - int(torch.randint(0, max(1, n // 3), (1,), generator=gen)))
    F = torch.randn(B, n, r, generator=gen, dtype=torch.float64) / r**0.5
    F32 = F.float()
    A = F32 @ F32.mT
    w = torch.randn(B, r, generator=gen, dtype=torch.float64)
    q = (F @ w[..., None])[..., 0]
    mu = mu_scale * torch.rand(B, K, generator=gen, dtype=torch.float64)
    lower = (
        0.3
        * torch.rand(B, K, generator=gen, dtype=torch.float64)
        * (torch.rand(B, K, generator=gen, dtype=torch.float64) < 0.3)
    )
    return A.float(), q.float(), mu.float(), lower.float(), F, w


def run_near_psd_benchmark(total: int = 100_000, batch: int = 1000, seed: int = 0) -> dict:
    """Solve ``total`` near-PSD problems, spread over TASK_SIZES and both dtypes, forward and backward; print and
    return the status counts, the worst feasibility violation and the time per problem.  No failure is allowed:
    the function raises if any problem fails."""
    check_counts(n=total, batch=batch)
    gen = torch.Generator().manual_seed(seed)
    counts = {s.name: 0 for s in Status}
    worst = {"float32": 0.0, "float64": 0.0}
    solved = 0
    t0 = time.perf_counter()
    while solved < total:
        for K, d in TASK_SIZES:
            for dtype in (torch.float32, torch.float64):
                B = min(batch, total - solved)
                if B <= 0:
                    break
                A, q, mu, lower, _, _ = near_psd_instance(gen, B, K, d)
                ins = [t.to(dtype).clone().requires_grad_() for t in (A, q, mu, lower)]
                f, info = solve_cone_qp(*ins, on_failure="count", return_info=True)
                f.sum().backward()
                if (
                    not all(t.grad is not None and torch.isfinite(t.grad).all() for t in ins)
                    or not torch.isfinite(f).all()
                ):
                    raise AssertionError(f"non-finite solution or gradient (K = {K}, d = {d}, {dtype})")
                for s in Status:
                    counts[s.name] += int((info.status == s).sum())
                fk = f.detach().double().view(B, K, d)
                scale = fk.abs().amax().clamp_min(1.0)
                viol = (lower.double() - fk[..., 0]).clamp_min(0).amax() / scale
                if d > 1:
                    viol = max(viol, (fk[..., 1:].norm(dim=-1) - mu.double() * fk[..., 0]).clamp_min(0).amax() / scale)
                key = str(dtype).removeprefix("torch.")
                worst[key] = max(worst[key], float(viol))
                solved += B
    seconds = time.perf_counter() - t0
    result = {"problems": solved, "status": counts, "worst_violation": worst, "us_per_problem": 1e6 * seconds / solved}
    print(f"{solved} near-PSD problems (sizes {TASK_SIZES}, float32 and float64), forward + backward:")
    print(f"  status counts {counts}")
    print(
        "  worst cone/bound violation relative to max(1, |f|): " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items())
    )
    print(f"  {result['us_per_problem']:.1f} µs per problem ({seconds:.1f} s)")
    failures = sum(v for k, v in counts.items() if Status[k] >= Status.MAX_ITER)
    if failures:
        raise AssertionError(f"{failures} near-PSD problems failed: {counts}")
    return result
