"""Independent references for the contact solver tests: random instances and a Clarabel solve."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

# Named tolerances of the solver tests (relative to the scale max(1, ‖f‖∞) of the solution).
TOL_F = 1e-8  # agreement of f (or of A·f where the minimiser is not unique) with Clarabel
TOL_OBJ = 1e-8  # agreement of the objective with Clarabel (relative to max(1, |obj|, ‖q‖∞·‖f‖∞))
TOL_KKT = 1e-9  # KKT residuals of our solution
CLARABEL_TOL = 1e-10


def random_instance(
    gen: torch.Generator, B: int, K: int, d: int, *, rank: int | None = None, scale: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random PSD A (rank ``rank`` or full), q, mu (a third of them 0) and lower (half of them 0); float64."""
    n = K * d
    r = rank or n
    M = torch.randn(B, n, r, generator=gen, dtype=torch.float64)
    A = scale * (M @ M.mT) / r
    if rank is None:
        q = scale * torch.randn(B, n, generator=gen, dtype=torch.float64)
    else:  # q in the range of A, as J v is in the range of J M̂⁻¹ Jᵀ: the problem stays bounded
        q = scale * (M @ torch.randn(B, r, 1, generator=gen, dtype=torch.float64))[..., 0]
    mu = 1.2 * torch.rand(B, K, generator=gen, dtype=torch.float64)
    mu = mu * (torch.rand(B, K, generator=gen) > 0.33)
    lower = 0.5 * torch.rand(B, K, generator=gen, dtype=torch.float64) * (torch.rand(B, K, generator=gen) > 0.5)
    return A, q, mu, lower


def _cvxpy():
    """cvxpy with the Clarabel solver, or skip the calling test."""
    pytest.importorskip("clarabel")
    return pytest.importorskip("cvxpy")


def clarabel_solve(A: np.ndarray, q: np.ndarray, mu: np.ndarray, lower: np.ndarray, d: int):
    """Solve one instance with Clarabel (through cvxpy) at CLARABEL_TOL; returns (f, objective).  The calling test
    is skipped where cvxpy or Clarabel (the ``reference`` extra) is not installed."""
    cp = _cvxpy()

    n = A.shape[0]
    K = n // d
    A = 0.5 * (A + A.T)
    f = cp.Variable(n)
    cons = [f[0::d] >= lower]
    if d > 1:
        for i in range(K):  # a zero-width cone is written as an equality: conic solvers need an interior
            ft = f[i * d + 1 : (i + 1) * d]
            cons.append(ft == 0 if mu[i] == 0 else cp.norm(ft) <= mu[i] * f[i * d])
    prob = cp.Problem(cp.Minimize(0.5 * cp.quad_form(f, cp.psd_wrap(A)) + q @ f), cons)
    for tol in (CLARABEL_TOL, 10 * CLARABEL_TOL, 100 * CLARABEL_TOL):  # Clarabel may stall at the tightest
        try:
            with warnings.catch_warnings():  # "may be inaccurate": handled by the status check below
                warnings.simplefilter("ignore", UserWarning)
                prob.solve(
                    solver="CLARABEL", tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol, tol_ktratio=1e-6, max_iter=500
                )
        except cp.error.SolverError:
            continue
        if prob.status == "optimal":
            return np.asarray(f.value), float(0.5 * f.value @ A @ f.value + q @ f.value)
    raise AssertionError(f"Clarabel did not solve the reference instance: {prob.status}")


def kkt_residual(A, q, mu, lower, f, d):
    """Largest violation of the optimality conditions of one instance, relative to max(1, ‖f‖∞).

    Checks feasibility, and that −(Af + q) lies in the normal cone of the constraint set at f: with
    g = Af + q, per contact the normal force obeys g_n·(f_n − lower) = 0 when f is strictly inside the cone, and
    the tangential velocity is opposed by friction when sliding.  Computed from the projected-gradient fixed
    point  f = Π(f − t·g)  for the per-contact set, whose projection is found by a fine 1-D search.
    """
    scale = max(1.0, float(np.abs(f).max()))
    K = len(mu)
    g = A @ f + q
    fk, gk = f.reshape(K, d), g.reshape(K, d)
    worst = 0.0
    for i in range(K):
        worst = max(worst, lower[i] - fk[i, 0])
        if d > 1:
            worst = max(worst, np.linalg.norm(fk[i, 1:]) - mu[i] * fk[i, 0])
        # stationarity: the per-contact problem min g_iᵀ y over the set, linearised at f_i
        y = _project(fk[i] - gk[i], mu[i], lower[i], d)
        worst = max(worst, float(np.abs(y - fk[i]).max()))
    return worst / scale


def _project(x, mu, lower, d):
    """Euclidean projection of x onto {y_n ≥ lower, ‖y_t‖ ≤ mu·y_n}."""
    if d == 1:
        return np.array([max(x[0], lower)])
    xn, xt = x[0], x[1:]
    r = np.linalg.norm(xt)
    u = xt / r if r > 0 else np.zeros_like(xt)
    # the projection keeps the tangential direction: 2-D problem in (y_n, y_r) with y_r ≥ 0
    candidates = []
    # 1) inside: x itself
    if xn >= lower and r <= mu * xn:
        return x.copy()
    # 2) on the cone surface (y_r = mu y_n), y_n ≥ lower
    yn = (xn + mu * r) / (1 + mu * mu)
    yn = max(yn, lower)
    candidates.append(np.concatenate([[yn], mu * yn * u]))
    # 3) on the plane y_n = lower, with y_r ≤ mu·lower
    candidates.append(np.concatenate([[lower], min(r, mu * lower) * u]))
    best = min(candidates, key=lambda y: np.linalg.norm(y - x))
    return best


def clarabel_min_norm(A: np.ndarray, q: np.ndarray, mu: np.ndarray, lower: np.ndarray, d: int, f_opt: np.ndarray):
    """The minimum-norm minimiser of a problem with a singular PSD A, in two stages: every minimiser has the
    range part of ``f_opt`` (a minimiser, from :func:`clarabel_solve`), so minimise ‖f‖ over the cones with that
    range part fixed.  Returns f (the calling test is skipped without cvxpy and Clarabel)."""
    cp = _cvxpy()

    n = A.shape[0]
    K = n // d
    evals, V = np.linalg.eigh(0.5 * (A + A.T))
    VR = V[:, evals > 1e-9 * max(evals.max(), 1e-300)]
    f = cp.Variable(n)
    cons = [f[0::d] >= lower, VR.T @ f == VR.T @ f_opt]
    if d > 1:
        for i in range(K):
            ft = f[i * d + 1 : (i + 1) * d]
            cons.append(ft == 0 if mu[i] == 0 else cp.norm(ft) <= mu[i] * f[i * d])
    prob = cp.Problem(cp.Minimize(cp.sum_squares(f)), cons)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        prob.solve(solver="CLARABEL", tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, max_iter=500)
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise AssertionError(f"Clarabel did not solve the minimum-norm stage: {prob.status}")
    return np.asarray(f.value)
