"""The compiled pieces of the solver against plain numpy: the reduced KKT solves and the scaling (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from solver_oracle import random_instance

from diffcontact.solver import kernel, kkt, least_norm, scaling, solve_cone_qp
from diffcontact.solver.kkt import contact_dims
from diffcontact.solver.problem import ConeQP, SolveOptions, _solve_with_retries


def _solved_batch(K, d, seed):
    """A solved standard-form batch with frictionless, inactive and lower-bounded contacts mixed in."""
    gen = torch.Generator().manual_seed(seed)
    B = 12
    A, q, mu, lower = random_instance(gen, B, K, d)
    mu[:3] = 0.0
    active = torch.rand(B, K, generator=gen) > 0.2
    return _solve_with_retries(ConeQP(A, q, mu, lower, active, d), SolveOptions(1e-10, 1e-7, 60, "count"))[1]


@pytest.mark.parametrize("d", [1, 2, 3])
def test_reduced_adjoint_solve_matches_dense(d):
    """The kernel's adjoint (exact reduction to n + K unknowns, LU per lane) against the dense Kᵀ x = [g; 0]."""
    res = _solved_batch(4, d, seed=7 * d)
    B, K = res.on.shape
    n = K * d
    N = n + K + K * d
    g = np.random.default_rng(d).standard_normal((B, n))
    arrays = [kernel.scaled_matrix(res.A, res.T), res.s_l, res.lam_l, res.s_q, res.lam_q, res.on, res.on_l]
    u, v_l, ok = kernel.adjoint(res, g)
    checked = 0
    for b in range(B):
        M = np.empty((N, N))
        kkt._kkt_matrix(*(a[b] for a in arrays), contact_dims(d), False, M)
        if np.linalg.cond(M) > 1e10:  # (an exactly degenerate element: the weak variant, tested elsewhere)
            continue
        assert ok[b]
        ref = np.linalg.solve(M.T, np.concatenate([g[b], np.zeros(N - n)]))
        scale = max(1.0, np.abs(ref).max())
        assert np.abs(u[b] - ref[:n]).max() <= 1e-9 * scale
        assert np.abs(v_l[b] - ref[n : n + K]).max() <= 1e-9 * scale
        checked += 1
    assert checked >= B // 2


def _scaling_reference(A, q, mu, lower, active, d):
    """The substitution written out with numpy, one element at a time."""
    B, K = mu.shape
    n = K * d
    out = {k: [] for k in ("P", "c", "l_hat", "T", "gamma", "lower_scale", "on_q", "on_l")}
    for b in range(B):
        As = 0.5 * (A[b] + A[b].T)
        on = active[b]
        a_nn = np.where(on, np.diag(As)[::d], 0.0)
        a_ref = a_nn.max() if a_nn.max() > 0 else 1.0
        sigma = 1.0 / np.sqrt(np.where(a_nn > 1e-12 * a_ref, a_nn, a_ref))
        D = np.ones((K, d))
        D[:, 1:] = mu[b][:, None]
        S = np.repeat(sigma * on, d)
        T = S * D.reshape(n)
        estimate = (np.maximum(lower[b] / sigma, -S[::d] * q[b][::d]) * on).max()
        c_abs = np.abs(T * q[b]).max()
        gamma = max(estimate, 1e-3 * c_abs) if estimate > 0 else c_abs
        gamma = gamma if gamma > 0 else 1.0
        keep = on & (lower[b] >= 1e-12 * sigma * gamma)
        low = np.where(keep, lower[b], 0.0)
        zero_mu = on & (mu[b] == 0) if d > 1 else np.zeros(K, bool)
        P = T[:, None] * As * T[None, :]
        pinned = np.zeros((K, d))
        pinned[:, 1:] = zero_mu[:, None]
        P += np.diag(np.repeat(1.0 - on, d) + pinned.reshape(n))
        out["P"].append(P)
        out["c"].append(T * q[b] / gamma)
        out["l_hat"].append(low / (sigma * gamma) * on)
        out["T"].append(T)
        out["gamma"].append(gamma)
        out["lower_scale"].append(keep / (sigma * gamma))
        out["on_q"].append(on & ~zero_mu if d > 1 else np.zeros(K, bool))
        out["on_l"].append(on & ((low > 0) | zero_mu) if d > 1 else on)
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("d", [1, 2, 3])
def test_scaling_matches_its_formulas(d):
    gen = torch.Generator().manual_seed(40 + d)
    A, q, mu, lower = (t.numpy() for t in random_instance(gen, 20, 3, d))
    mu[:4, 0] = 0.0  # frictionless contacts
    lower[4:8, 1] = 1e-15  # negligible lower bounds
    A[8:10, :d, :] = 0.0  # a contact with no inverse inertia
    A[8:10, :, :d] = 0.0
    active = np.random.default_rng(d).random((20, 3)) > 0.25
    active[10] = False  # all contacts inactive
    got = scaling.scale_batch(A, q, mu, lower, active, contact_dims(d))
    names = ("A", "c", "l_hat", "T", "S", "gamma", "sigma", "lower_scale", "on_q", "on_l", "zero_mu")
    got = dict(zip(names, got))
    got["P"] = kernel.scaled_matrix(got["A"], got["T"])  # (as the kernel forms it)
    ref = _scaling_reference(A, q, mu, lower, active, d)
    for key, value in ref.items():
        if value.dtype == bool:
            assert (got[key] == value).all(), key
        else:
            np.testing.assert_allclose(got[key], value, rtol=1e-13, atol=1e-300, err_msg=key)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_without_gradients_the_same_solution(dtype):
    """The path without an autograd Function (no_grad, or no input requiring a gradient) returns f bit for bit."""
    gen = torch.Generator().manual_seed(11)
    A, q, mu, lower = (t.to(dtype) for t in random_instance(gen, 9, 3, 3))
    active = torch.rand(9, 3, generator=gen) > 0.2
    with_grad = solve_cone_qp(A, q.clone().requires_grad_(), mu, lower, active)
    with torch.no_grad():
        without = solve_cone_qp(A, q.clone().requires_grad_(), mu, lower, active)
    plain = solve_cone_qp(A, q, mu, None if dtype == torch.float32 else lower, active)
    assert with_grad.requires_grad and not without.requires_grad and not plain.requires_grad
    assert without.dtype == plain.dtype == dtype
    assert torch.equal(with_grad.detach(), without)
    if dtype == torch.float64:
        assert torch.equal(without, plain)


@pytest.mark.parametrize("d, K", [(1, 3), (2, 3), (3, 3), (3, 11)])
def test_flat_test_against_eigenvalues(d, K):
    """``least_norm.flat_elements`` (Cholesky on the rows in use, A symmetrised on the fly; in the kernel, by panels
    of 8 columns) against the eigenvalues of the symmetrised A on the rows of ``least_norm.rows_in_use``, at every
    lane width this CPU runs (B not a multiple of any); and its flags of finite and of exactly symmetric matrices."""
    gen = torch.Generator().manual_seed(50 + d + K)
    B, tol = 41, 1e-6
    A, q, mu, lower = random_instance(gen, B, K, d)
    rank = max(1, K * d - 3) if K <= 3 else K * d // 3  # singular (flat on most row sets)
    A[: B // 2] = random_instance(gen, B // 2, K, d, rank=rank)[0]
    skew = torch.randn(B, K * d, K * d, generator=gen, dtype=torch.float64)
    odd = (torch.arange(B) % 2 == 1)[:, None, None]
    A = torch.where(odd, A + 0.1 * (skew - skew.mT), 0.5 * (A + A.mT))  # odd: not symmetric (symmetric part as above)
    active = torch.rand(B, K, generator=gen) > 0.2
    used = least_norm.rows_in_use(mu, active, d).numpy()
    sym = 0.5 * (A + A.mT).numpy()
    expected = np.zeros(B, dtype=bool)
    for b in range(B):
        rows = np.flatnonzero(used[b])
        if len(rows):
            sub = sym[b][np.ix_(rows, rows)]
            expected[b] = np.linalg.eigvalsh(sub)[0] <= tol * max(sub.diagonal().max(), 0.0)
    assert expected.sum() >= 5 and (~expected).sum() >= 5
    width = kernel.current_width()
    try:
        for w in kernel.supported_widths():
            kernel.select_width(w)
            got, finite, symmetric = least_norm.flat_elements(
                np.ascontiguousarray(A.numpy()), mu.numpy(), active.numpy(), d, tol
            )
            assert (got == expected).all(), f"lane width {w}"
            assert finite.all() and (symmetric == ~odd.flatten().numpy()).all(), f"lane width {w}"
    finally:
        kernel.select_width(width)
