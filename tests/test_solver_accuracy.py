"""The contact solver against Clarabel, closed-form cases and KKT conditions (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from solver_oracle import TOL_OBJ, clarabel_solve, kkt_residual, random_instance

from diffcontact.solver import Status, solve_cone_qp

# Clarabel itself (at 1e-10) leaves errors of up to a few 1e-6 along the boundary of a friction cone (its
# solutions' KKT residuals, by the independent checker, reach 4e-6), while ours are polished to ~1e-12.  So f
# is compared within TOL_F plus ten times Clarabel's own KKT residual, and our KKT residual is checked directly.
TOL_F = 1e-8
TOL_KKT = 1e-9

CASES = [(K, d, rank_def) for K in (1, 2, 3, 5, 19) for d in (1, 2, 3) for rank_def in (False, True)]


@pytest.mark.parametrize("K,d,rank_def", CASES)
def test_agrees_with_clarabel(K, d, rank_def):
    """34 instances per case, 30 cases: 1020 random instances in all."""
    gen = torch.Generator().manual_seed(1000 * K + 10 * d + rank_def)
    B, n = 34, K * d
    A, q, mu, lower = random_instance(gen, B, K, d, rank=max(1, n // 2) if rank_def else None)
    f, info = solve_cone_qp(A, q, mu, lower, return_info=True)
    assert (info.status == Status.CONVERGED).all()
    for b in range(B):
        An, qn, mun, ln, fb = A[b].numpy(), q[b].numpy(), mu[b].numpy(), lower[b].numpy(), f[b].numpy()
        f_ref, obj_ref = clarabel_solve(An, qn, mun, ln, d)
        scale = max(1.0, np.abs(f_ref).max())
        obj = 0.5 * fb @ An @ fb + qn @ fb
        obj_scale = max(1.0, abs(obj_ref), np.abs(qn).max() * scale)
        assert abs(obj - obj_ref) <= TOL_OBJ * obj_scale, (b, obj, obj_ref)
        tol_f = TOL_F + 10 * kkt_residual(An, qn, mun, ln, f_ref, d)
        if rank_def:  # the minimiser is not unique: compare the physical result A·f
            assert np.abs(An @ (fb - f_ref)).max() <= tol_f * scale, b
        else:
            assert np.abs(fb - f_ref).max() <= tol_f * scale, b
        assert kkt_residual(An, qn, mun, ln, fb, d) <= TOL_KKT, b


def test_polishing_damps_newton_steps_that_overshoot():
    """Where a contact's multipliers are small next to its force (a contact that barely slides), the full Newton step
    of polishing from the interior-point solution raises the residual; the step is then halved until it lowers it.
    Of the K = 19, d = 2 bench instances, eleven stayed at 3e-10 … 1.3e-6 after polishing with any number of steps
    (and needed the second pass); with halved steps every element reaches rounding level, and those eleven agree with
    Clarabel."""
    from diffcontact.bench.solver import _instances
    from diffcontact.solver import kernel, problem, scaling
    from diffcontact.solver.kkt import contact_dims

    K, d = 19, 2
    A, q, mu, lower = _instances(torch.Generator().manual_seed(0), 800, K, d)
    arrays = problem._as_arrays(A, q, mu, lower, None)
    A_sym, c, l_hat, T, _, gamma, *_, on_q, on_l, _ = scaling.scale_batch(*arrays, contact_dims(d))
    res = kernel.solve(
        A_sym, T, c, l_hat, on_q, on_l, d, ipm_tol=problem.IPM_TOL, final_tol=problem.ROUNDING_TOL,
        acceptable_tol=1e-7, max_iter=60, refine_tol=problem.IPM_TOL, start_margin=problem.START_MARGIN,
        polish_steps=6,
    )  # fmt: skip
    assert (res.status == Status.CONVERGED).all(), np.flatnonzero(res.status)
    f = gamma[:, None] * T * res.z
    for b in (120, 178, 228, 280, 332, 419, 463, 471, 557, 567, 654):
        An, qn, mun, ln = (t[b].numpy() for t in (A, q, mu, lower))
        f_ref, obj_ref = clarabel_solve(An, qn, mun, ln, d)
        scale = max(1.0, np.abs(f_ref).max())
        assert np.abs(f[b] - f_ref).max() <= (TOL_F + 10 * kkt_residual(An, qn, mun, ln, f_ref, d)) * scale, b
        assert kkt_residual(An, qn, mun, ln, f[b], d) <= TOL_KKT, b


def test_frictionless_single_contact_closed_form():
    gen = torch.Generator().manual_seed(0)
    B = 200
    A = torch.rand(B, 1, 1, generator=gen, dtype=torch.float64) * 10 + 1e-3
    q = torch.randn(B, 1, generator=gen, dtype=torch.float64)
    lower = torch.rand(B, 1, generator=gen, dtype=torch.float64) * (torch.rand(B, 1, generator=gen) > 0.5)
    f = solve_cone_qp(A, q, torch.zeros(B, 1, dtype=torch.float64), lower)
    exact = torch.maximum(lower, (-q / A[:, 0]).clamp_min(0))
    assert torch.allclose(f, exact, rtol=TOL_F, atol=TOL_F)


@pytest.mark.parametrize("d", [2, 3])
def test_sticking_and_sliding_single_contact(d):
    """A = m⁻¹ I: stick if ‖q_t‖ ≤ μ·(−q_n), f = −m q; else slide: f_t = −μ f_n q̂_t with
    f_n = (−q_n + μ‖q_t‖) / (m⁻¹(1 + μ²)) (the convex model presses harder to slide: paper Eq. 15)."""
    m_inv, mu = 2.0, 0.5
    A = (m_inv * torch.eye(d, dtype=torch.float64)).expand(2, d, d).clone()
    q = torch.zeros(2, d, dtype=torch.float64)
    q[:, 0] = -1.0  # approaching at unit speed
    q[0, 1] = 0.3  # slow tangential speed: sticks
    q[1, 1] = 2.0  # fast: slides
    if d == 3:
        q[:, 2] = 0.1
    f = solve_cone_qp(A, q, torch.full((2, 1), mu, dtype=torch.float64))
    stick = -q[0] / m_inv
    assert torch.allclose(f[0], stick, atol=1e-9)
    qt = q[1, 1:]
    fn = float((1.0 + mu * qt.norm()) / (m_inv * (1 + mu**2)))
    slide = torch.cat([torch.tensor([fn], dtype=torch.float64), -mu * fn * qt / qt.norm()])
    assert torch.allclose(f[1], slide, atol=1e-8)


def test_inactive_contacts_are_zero_and_do_not_interact():
    gen = torch.Generator().manual_seed(3)
    A, q, mu, lower = random_instance(gen, 16, 5, 2)
    active = torch.rand(16, 5, generator=gen) > 0.4
    f = solve_cone_qp(A, q, mu, lower, active)
    rows = active.repeat_interleave(2, -1)
    assert (f[~rows] == 0).all()
    for b in range(4):  # the same as solving the active sub-problem alone
        idx = rows[b].nonzero().flatten()
        k = active[b].nonzero().flatten()
        if len(k) == 0:
            continue
        sub = solve_cone_qp(A[b][idx][:, idx][None], q[b][idx][None], mu[b][k][None], lower[b][k][None])
        assert torch.allclose(f[b][idx], sub[0], rtol=0, atol=1e-13)  # (measured: equal)


def test_float32_input_returns_float32():
    gen = torch.Generator().manual_seed(4)
    A, q, mu, lower = random_instance(gen, 8, 3, 3)
    f64 = solve_cone_qp(A, q, mu, lower)
    f32 = solve_cone_qp(A.float(), q.float(), mu.float(), lower.float())
    assert f32.dtype == torch.float32
    assert torch.allclose(f32.double(), f64, rtol=1e-4, atol=1e-4)


def test_scale_invariance():
    """f(sA, sq) = f(A, q) and f(A, sq, s·lower) = s·f(A, q, lower) over 12 orders of magnitude."""
    gen = torch.Generator().manual_seed(5)
    A, q, mu, lower = random_instance(gen, 8, 3, 2)
    f = solve_cone_qp(A, q, mu, lower)
    for s in (1e-6, 1e6):  # (measured: within 8e-14 for |f| up to 21)
        assert torch.allclose(solve_cone_qp(s * A, s * q, mu, lower), f, rtol=1e-12, atol=1e-12)
        g = solve_cone_qp(A, s * q, mu, s * lower)
        assert torch.allclose(g / s, f, rtol=1e-12, atol=1e-12)
