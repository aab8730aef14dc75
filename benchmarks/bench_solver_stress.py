"""Contact-solver stress run: random degenerate problems in batches, counted by status; every converged element is
checked independently, so that a wrong answer reported as converged (a silent failure) is caught.

    OMP_NUM_THREADS=1 python benchmarks/bench_solver_stress.py [--total 1000000] [--batch 1000] [--seed 0]
        [--kinds KIND ...] [--calls N ...]

A silent failure or crash is printed with its call number (and element); ``--calls N`` replays call N of the same
run alone (the same draws; only that call is solved).

Each batch draws K (1 to 20 contacts, most of them small), d (1, 2 or 3) and one kind of trouble:

- ``scaled``: A of random scale 1e-12 … 1e12 (huge or tiny masses), q of its own random scale;
- ``singular``: A = F Fᵀ of rank below K·d (more contact rows than degrees of freedom), perturbed by ±1e-9·‖A‖ in
  its null space (PSD up to rounding only), q = F w in its range (a velocity that obeys the joints:
  solver/least_norm.py);
  checked against the unperturbed A;
- ``ill``: A with eigenvalues spread over 1e-5 … 1 (near-singular, above the flat threshold 1e-6 of float64);
- ``infinite_mass``: A = 0 (every body immovable): converged where q pushes the contacts apart, else unbounded;
- ``mu0`` / ``large_mu`` / ``huge_mu``: μ = 0 everywhere, or μ of 10 … 1e3, or 1e3 … 1e100;
- ``mixed``: lower bounds e·f_n > 0 on some contacts, inactive contacts, μ = 0 on some;
- ``float32``: the ``mixed`` problems in single precision;
- ``nonfinite``: a NaN or inf in A, q, μ or the lower bounds of one element (the whole call must be refused with a
  ValueError naming it);
- ``zero_mass``: an infinite entry in A (a body of zero mass): refused as non-finite.

A converged element is checked against the optimality conditions of the cone QP, independently of the solver: its
natural residual ‖f − Π(f − α(Af + q))‖ (Π the projection onto the feasible set {f_n ≥ l, ‖f_t‖ ≤ μ f_n}, α = 1/‖A‖)
relative to the solution's size, and zero impulses on inactive contacts.  An element is a silent failure if it is
reported CONVERGED (or INACCURATE, usable) and is NaN or fails this check; a crash is any exception other than the
documented refusals (ValueError, TypeError, IndefiniteMatrixError).
"""

from __future__ import annotations

import diffcontact  # (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import collections
import os
import platform
import time

import numpy as np
import torch

from diffcontact.errors import IndefiniteMatrixError
from diffcontact.solver import Status, solve_cone_qp

KINDS = (
    "scaled", "singular", "ill", "infinite_mass", "mu0", "large_mu", "huge_mu", "mixed", "float32", "nonfinite",
    "zero_mass",
)  # fmt: skip
CONTACTS = np.array([1, 2, 3, 4, 5, 6, 8, 10, 12, 15, 20])
CONTACT_WEIGHTS = np.array([20, 16, 12, 10, 8, 6, 4, 3, 2, 1, 1], dtype=float)
TOL = {torch.float64: 1e-6, torch.float32: 1e-3}  # relative natural residual accepted for a usable answer


def psd(rng: np.random.Generator, B: int, n: int, rank: int, spread: float = 0.0) -> np.ndarray:
    """B random PSD (n, n) matrices of rank ``rank``, eigenvalues log-uniform over [10^-spread, 1]."""
    Q, _ = np.linalg.qr(rng.standard_normal((B, n, n)))
    lam = 10.0 ** (-spread * rng.random((B, n)))
    lam[:, rank:] = 0.0
    return (Q * lam[:, None, :]) @ Q.transpose(0, 2, 1)


def instance(rng: np.random.Generator, kind: str, B: int, K: int, d: int):
    """(A, A_exact, q, mu, lower, active) as float64 arrays for one batch of ``kind``: A is given to the solver,
    A_exact (the same but for a rounding perturbation) checks its answer."""
    n = K * d
    A = psd(rng, B, n, n, spread=2.0)
    q = rng.standard_normal((B, n))
    mu = 1.5 * rng.random((B, K))
    lower = np.zeros((B, K))
    active = np.ones((B, K), dtype=bool)
    exact = None
    if kind == "scaled":
        A *= 10.0 ** rng.uniform(-12, 12, (B, 1, 1))
        q *= 10.0 ** rng.uniform(-6, 6, (B, 1))
    elif kind == "singular":
        rank = int(rng.integers(1, n)) if n > 1 else 1
        exact = psd(rng, B, n, rank, spread=1.0)
        w, V = np.linalg.eigh(exact)
        null = V[..., : n - rank]
        q = (exact @ rng.standard_normal((B, n, 1)))[..., 0]
        A = exact + rng.choice([-1.0, 1.0], (B, 1, 1)) * 1e-9 * w[..., -1:, None] * (null @ null.transpose(0, 2, 1))
        A = 0.5 * (A + A.transpose(0, 2, 1))
    elif kind == "ill":
        A = psd(rng, B, n, n, spread=5.0)
    elif kind == "infinite_mass":
        A = np.zeros((B, n, n))
    elif kind == "mu0":
        mu[:] = 0.0
    elif kind == "large_mu":
        mu = 10.0 ** rng.uniform(1, 3, (B, K))
    elif kind == "huge_mu":
        mu = 10.0 ** rng.uniform(3, 100, (B, K))
    elif kind in ("mixed", "float32"):
        lower = 0.3 * rng.random((B, K)) * (rng.random((B, K)) < 0.3)
        active = rng.random((B, K)) < 0.8
        mu[rng.random((B, K)) < 0.3] = 0.0
    elif kind == "nonfinite":
        which = int(rng.integers(4))
        arr = (A, q, mu, lower)[which]
        arr.reshape(B, -1)[int(rng.integers(B)), int(rng.integers(arr[0].size))] = rng.choice([np.nan, np.inf, -np.inf])
    elif kind == "zero_mass":
        i = int(rng.integers(n))
        A[int(rng.integers(B)), i, i] = np.inf
    return A, (A if exact is None else exact), q, mu, lower, active


def project(y: np.ndarray, mu: np.ndarray, lower: np.ndarray, d: int) -> np.ndarray:
    """Projection of y (B, K, d) onto {f_n ≥ l, ‖f_t‖ ≤ μ f_n} per contact (for d = 1: f_n ≥ l)."""
    yn = y[..., 0]
    if d == 1:
        return np.maximum(yn, lower)[..., None]
    yt = y[..., 1:]
    t = np.linalg.norm(yt, axis=-1)
    # projection onto the cone ‖f_t‖ ≤ μ f_n
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # (μ up to 1e100: products overflow to inf)
        inside = t <= mu * yn
        polar = mu * t <= -yn  # (in the polar cone: projects to 0)
        # onto the boundary: normal part a = (y_n + μt)/(1 + μ²), tangential magnitude μa, without overflow
        big = mu > 1
        inv = np.where(big, 1 / np.where(big, mu, 1), 0.0)
        a = np.where(big, (yn * inv + t) * inv / (1 + inv**2), (yn + mu * t) / (1 + mu**2))
        m = np.where(big, (yn * inv + t) / (1 + inv**2), mu * a)
        unit = np.where(t[..., None] > 0, yt / np.where(t > 0, t, 1)[..., None], 0.0)
    pn = np.where(inside, yn, np.where(polar, 0.0, a))
    pt = np.where(inside[..., None], yt, np.where(polar[..., None], 0.0, m[..., None] * unit))
    # below the lower bound: onto the disk f_n = l, ‖f_t‖ ≤ μ l
    below = pn < lower
    radius = mu * lower
    clipped = np.where((t > radius)[..., None], radius[..., None] * unit, yt)
    pn = np.where(below, lower, pn)
    pt = np.where(below[..., None], clipped, pt)
    return np.concatenate([pn[..., None], pt], -1)


def residual(A, q, mu, lower, active, f, d) -> np.ndarray:
    """Relative natural residual (B,) of the solutions f (B, n) of the problems (inactive contacts removed)."""
    B, n = q.shape
    K = n // d
    scale = np.abs(np.diagonal(A, axis1=1, axis2=2)).max(-1)
    g = (A @ f[..., None])[..., 0] + q
    alpha = 1.0 / np.where(scale > 0, scale, 1.0)  # (any α > 0: the residual is 0 exactly at a solution)
    y = (f - alpha[:, None] * g).reshape(B, K, d)
    p = project(y, mu, lower, d).reshape(B, n)
    keep = np.repeat(active, d, axis=1)
    r = np.where(keep, f - p, f)  # (an inactive contact's impulse must be 0)
    size = np.maximum.reduce(
        [np.abs(f).max(-1), alpha * np.abs(q).max(-1), lower.max(-1, initial=0.0), np.full(B, 1e-30)]
    )
    return np.abs(r).max(-1) / size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--total", type=int, default=1_000_000, help="problems in all")
    parser.add_argument("--batch", type=int, default=1000, help="problems per solver call")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", nargs="*", default=list(KINDS), choices=KINDS, help="kinds of trouble (all)")
    parser.add_argument(
        "--calls", nargs="*", type=int, default=None, help="solve only these calls (numbers as printed) of the run"
    )
    args = parser.parse_args()
    kinds = args.kinds
    rng = np.random.default_rng(args.seed)
    counts: dict[str, collections.Counter] = {k: collections.Counter() for k in KINDS}
    silent: list[tuple] = []
    silent_by: collections.Counter = collections.Counter()  # (kind, status) of the silent failures
    crashes: list[tuple] = []
    worst = {k: 0.0 for k in KINDS}
    done, calls, t0 = 0, 0, time.perf_counter()
    print(
        f"diffcontact {diffcontact.__version__}, torch {torch.__version__}, numpy {np.__version__}, "
        f"python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs, {torch.get_num_threads()} "
        f"torch threads; {args.total} problems in batches of up to {args.batch}, seed {args.seed}",
        flush=True,
    )
    while done < args.total:
        kind = kinds[calls % len(kinds)]
        K = int(rng.choice(CONTACTS, p=CONTACT_WEIGHTS / CONTACT_WEIGHTS.sum()))
        d = int(rng.integers(1, 4))
        B = min(args.batch, args.total - done)
        A, exact, q, mu, lower, active = instance(rng, kind, B, K, d)
        dtype = torch.float32 if kind == "float32" else torch.float64
        tensors = [torch.from_numpy(a).to(dtype) for a in (A, q, mu, lower)]
        calls += 1
        done += B
        if args.calls is not None and calls not in args.calls:  # (replay: the same draws, only these solved)
            continue
        try:
            f, info = solve_cone_qp(*tensors, torch.from_numpy(active), on_failure="count", return_info=True)
        except (ValueError, TypeError, IndefiniteMatrixError) as err:
            refused = "refused (non-finite)" if "non-finite" in str(err) else f"refused ({type(err).__name__})"
            counts[kind][refused] += B
            if kind not in ("nonfinite", "zero_mass") and "non-finite" in str(err):
                crashes.append((f"call {calls}", kind, K, d, f"unexpected refusal: {err}"))
            continue
        except Exception as err:  # noqa: BLE001  (counted: the goal is none)
            counts[kind]["crash"] += B
            crashes.append((f"call {calls}", kind, K, d, f"{type(err).__name__}: {err}"))
            continue
        if kind in ("nonfinite", "zero_mass"):
            crashes.append((f"call {calls}", kind, K, d, "a non-finite input was not refused"))
        status = info.status.numpy()
        for s, c in zip(*np.unique(status, return_counts=True)):
            counts[kind][Status(int(s)).name] += int(c)
        # the solution as returned (in the input's dtype), checked against the problem as given
        f64 = f.detach().to(torch.float64).numpy()
        args64 = [exact.astype(tensors[0].numpy().dtype).astype(np.float64)] + [
            t.to(torch.float64).numpy() for t in tensors[1:]
        ]
        usable = status <= Status.INACCURATE
        nan = ~np.isfinite(f64).all(-1)
        failed_not_zero = (~usable) & (np.abs(np.nan_to_num(f64, nan=1.0)).max(-1) > 0)
        res = residual(*args64, active, np.nan_to_num(f64), d)
        wrong = usable & (nan | (res > TOL[dtype]))
        if usable.any():
            worst[kind] = max(worst[kind], float(np.nan_to_num(res[usable], nan=np.inf).max()))
        for i in np.flatnonzero(wrong | failed_not_zero)[:3]:
            silent.append(
                (
                    f"call {calls}",
                    f"element {i}",
                    kind,
                    K,
                    d,
                    Status(int(status[i])).name,
                    float(res[i]),
                    "NaN" if nan[i] else "",
                )
            )
        counts[kind]["silent"] += int(wrong.sum() + failed_not_zero.sum())
        for i in np.flatnonzero(wrong | failed_not_zero):
            silent_by[(kind, Status(int(status[i])).name)] += 1
        if calls % 100 == 0:
            print(f"  {done} problems, {time.perf_counter() - t0:.0f} s", flush=True)
    seconds = time.perf_counter() - t0
    names = [s.name for s in Status] + ["refused (non-finite)", "refused (IndefiniteMatrixError)", "crash", "silent"]
    print(f"\n{done} problems in {calls} calls, {seconds:.0f} s ({1e6 * seconds / done:.0f} µs/problem, under load)")
    print("| kind | " + " | ".join(names) + " | worst relative residual of a usable answer |")
    print("|---" * (len(names) + 2) + "|")
    for kind in kinds:
        row = " | ".join(str(counts[kind].get(n, 0)) for n in names)
        print(f"| {kind} | {row} | {worst[kind]:.1e} |")
    total = collections.Counter()
    for c in counts.values():
        total.update(c)
    print(f"| all | {' | '.join(str(total.get(n, 0)) for n in names)} | |")
    print(f"\nsilent failures (a NaN or a wrong answer reported usable, or a failure not zero): {total['silent']}")
    print(f"  by kind and status: {dict(silent_by)}")
    print(f"crashes or unexpected outcomes: {len(crashes)}")
    for item in (silent + crashes)[:20]:
        print("  ", item)


if __name__ == "__main__":
    main()
