"""The compiled interior-point kernel: every lane width this CPU runs gives the same iterates (float64).

The widths with fused multiply-adds (8, 4) agree bit for bit; the 2-lane kernel rounds without them, which
moves the last iterates by about 1e-9."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from solver_oracle import random_instance

from diffcontact.solver import kernel, scaling, status
from diffcontact.solver.kkt import contact_dims
from diffcontact.solver.problem import IPM_TOL, START_MARGIN
from diffcontact.solver.status import Status


def _standard_form(K, d, B, seed):
    """A batch with frictionless, inactive and lower-bounded contacts mixed in, B not a multiple of any width."""
    gen = torch.Generator().manual_seed(seed)
    A, q, mu, lower = random_instance(gen, B, K, d)
    active = torch.rand(B, K, generator=gen) > 0.2
    active[0] = False  # an element without any contact
    arrays = scaling.scale_batch(A.numpy(), q.numpy(), mu.numpy(), lower.numpy(), active.numpy(), contact_dims(d))
    A_sym, c, l_hat, T, *_, on_q, on_l, _ = arrays
    return A_sym, T, c, l_hat, on_q, on_l


def _iterates(A, T, c, l_hat, on_q, on_l, d, trace, polish_steps=0):
    """The interior-point iterates alone (to 1e-8, no polishing), as tensors."""
    options = dict(acceptable_tol=1e-7, max_iter=60, start_margin=START_MARGIN, refine_tol=IPM_TOL)
    res = kernel.solve(
        A, T, c, l_hat, on_q, on_l, d, ipm_tol=1e-8, final_tol=1e-8, **options, polish_steps=polish_steps, trace=trace
    )
    return SimpleNamespace(**{name: torch.from_numpy(getattr(res, name)) for name in res.OUTPUTS})


@pytest.mark.parametrize("d,K", [(1, 4), (2, 3), (3, 5)])
def test_the_kernel_forms_p_by_its_stated_rule(d, K):
    """P = T·A·T formed in the kernel (with the identity on the rows where T = 0: inactive contacts, which the batch
    has) solves bit for bit as the same P formed in Python (``kernel.scaled_matrix``) and passed with T = 1."""
    A, T, *rest = _standard_form(K, d, B=23, seed=5 * d + K)
    assert (T == 0).any()
    P = kernel.scaled_matrix(A, T)
    got, ref = (_iterates(*ab, *rest, d, np.zeros((23, 0, 4)), 3) for ab in ((A, T), (P, np.ones_like(T))))
    for name in got.__dict__:
        assert torch.equal(getattr(got, name), getattr(ref, name)), name


@pytest.fixture
def restore_width():
    width = kernel.current_width()
    yield
    kernel.select_width(width)


@pytest.mark.parametrize("d,K", [(1, 4), (2, 3), (3, 5)])
def test_lane_widths_agree(d, K, restore_width):
    data = _standard_form(K, d, B=23, seed=11 * d + K)
    results = {}
    for width in kernel.supported_widths():
        kernel.select_width(width)
        trace = np.zeros((23, 8, 4))
        res = _iterates(*data, d, trace)
        results[width] = (res, trace)
    ref, ref_trace = results[kernel.supported_widths()[0]]
    assert (ref.status == Status.CONVERGED).all()
    assert ref.iterations[0] == 0 and (ref.z[0] == 0).all()
    assert (ref_trace[1:, 0, 2] > 0).all()  # the trace holds the gap of the first iterate
    for res, trace in results.values():
        assert torch.equal(res.status, ref.status) and torch.equal(res.iterations, ref.iterations)
        for name in ("z", "s_l", "lam_l", "s_q", "lam_q"):
            assert torch.allclose(getattr(res, name), getattr(ref, name), rtol=0, atol=1e-7), name
        # (the residuals of the last iterates are rounding errors amplified by the conditioning of W)
        assert np.allclose(trace[..., 2:], ref_trace[..., 2:], rtol=1e-5, atol=1e-8)
        assert np.allclose(trace[..., :2], ref_trace[..., :2], rtol=1e-5, atol=1e-6)


def test_unknown_width_is_refused(restore_width):
    with pytest.raises(ValueError, match="lane width 16: not a lane width"):
        kernel.select_width(16)


def test_bad_environment_variable_is_named(monkeypatch, restore_width):
    monkeypatch.setenv("DIFFCONTACT_LANES", "wide")
    with pytest.raises(ValueError, match="DIFFCONTACT_LANES='wide'"):
        kernel.select_width()


@pytest.mark.slow
def test_bad_environment_variable_does_not_break_the_import():
    """The width is chosen on first use: the import succeeds and the first solve names the variable."""
    code = (
        "import diffcontact, torch\n"
        "try:\n"
        "    diffcontact.solve_cone_qp(torch.eye(2)[None], -torch.ones(1, 2), torch.ones(1, 1))\n"
        "except ValueError as e:\n"
        "    print(e)\n"
    )
    env = {**os.environ, "DIFFCONTACT_LANES": "wide"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert "DIFFCONTACT_LANES='wide': not a lane width" in out.stdout


def test_python_and_kernel_agree_on_the_shared_facts():
    """Status codes, failure rule and weak-cone threshold: csrc/api.h against the Python copies."""
    got = kernel._lib.constants()
    assert {s.name: int(s) for s in Status} == {s.name: got[s.name.lower()] for s in Status}
    assert got["first_failure"] == status.FIRST_FAILURE
    assert got["weak_tol"] == status.WEAK_TOL
    assert got["api_version"] == kernel.API_VERSION
    assert [bool(status.is_failure(s)) for s in Status] == [False, False, True, True, True]


def test_kernel_refuses_arrays_that_do_not_fit_the_problem():
    """The module checks every array against B, K, d before the kernel reads it: a short, wrongly typed or
    non-contiguous array, an element index out of range or a bad range raise, naming the argument."""
    K, d, B = 2, 3, 5
    n = K * d
    A = np.tile(np.eye(n), (B, 1, 1))
    T, c, lower = np.ones((B, n)), np.tile([-1.0, 0.5, 0.0], (B, K)), np.zeros((B, K))  # (sticking contacts)
    on = np.ones((B, K), dtype=np.bool_)
    out = kernel.IPMResult(A, T, on, on, d)
    idx = np.arange(B, dtype=np.int64)
    options = (K, d, IPM_TOL, 1e-13, 1e-7, 60, START_MARGIN, IPM_TOL, 3)

    def solve(options=options, start=0, stop=B, **change):
        args = dict(A=A, T=T, c=c, lower=lower, on=on, on_l=on, idx=idx, trace=kernel._NO_TRACE, out=out._buffer)
        args.update(change)
        return kernel._lib.solve(*args.values(), *options, start, stop)

    solve()  # (the arguments as kernel.solve passes them)
    assert (out.status == Status.CONVERGED).all()
    np.testing.assert_allclose(out.z, np.tile([1.0, -0.5, 0.0], (B, K)), atol=1e-12)  # (unconstrained minimiser)
    with pytest.raises(ValueError, match="A has"):
        solve(A=A[:, :-1].copy())
    with pytest.raises(ValueError, match="c has"):
        solve(c=np.zeros((B, n), dtype=np.float32))
    with pytest.raises(ValueError, match="out has"):
        solve(out=np.zeros(out._buffer.size + 1))
    with pytest.raises(ValueError, match="element 5 of 5"):
        solve(idx=np.array([0, 5], dtype=np.int64), stop=2)
    with pytest.raises(ValueError, match="elements 0 ... 6 of 5"):
        solve(stop=6)
    with pytest.raises(ValueError, match="contiguous"):
        solve(T=np.ones((n, B)).T)
    with pytest.raises(ValueError, match="d = 4"):
        solve(options=(K, 4, *options[2:]))
    with pytest.raises(TypeError, match="takes 20 arguments"):
        kernel._lib.solve(A, T)
    with pytest.raises(ValueError, match="flags has"):
        kernel._lib.flat(A, lower, on, np.zeros(3 * B + 1, dtype=np.bool_), K, d, 1e-9, 0, B)
    with pytest.raises(ValueError, match="v_l has"):
        kernel._lib.adjoint(A, T, out._buffer, on, on, c, np.empty((B, n)), np.empty((B, 1)), np.empty(B, np.bool_),
                           K, d, 0, B)  # fmt: skip


@pytest.mark.parametrize("d", [2, 3])
def test_solution_does_not_depend_on_the_batch_around_it(d):
    """Lanes are independent: an element's solution and gradient are the same bit for bit whether it is solved
    alone, in a shuffled batch, or split among threads differently."""
    from diffcontact.solver import solve_cone_qp

    gen = torch.Generator().manual_seed(5 + d)
    A, q, mu, lower = random_instance(gen, 37, 3, d)
    f = solve_cone_qp(A, q, mu, lower)
    perm = torch.randperm(37, generator=gen)
    assert torch.equal(solve_cone_qp(A[perm], q[perm], mu[perm], lower[perm]), f[perm])
    for b in (0, 17, 36):
        assert torch.equal(solve_cone_qp(A[b : b + 1], q[b : b + 1], mu[b : b + 1], lower[b : b + 1])[0], f[b])
    # gradients too
    ins = [t.clone().requires_grad_() for t in (A, q, mu, lower)]
    solve_cone_qp(*ins).pow(2).sum().backward()
    one = [t[17:18].clone().requires_grad_() for t in (A, q, mu, lower)]
    solve_cone_qp(*one).pow(2).sum().backward()
    for a, b in zip(ins, one):
        assert torch.equal(a.grad[17:18], b.grad)


def test_degenerate_gradient_is_reproducible(monkeypatch):
    """An element whose adjoint needs the least-squares fallback (a singular K: rank-1 A in 3D) gets the same
    gradient bit for bit on every run and alone or in its batch (it varied in the last digits with
    torch.linalg.lstsq)."""
    from diffcontact.solver import implicit, solve_cone_qp

    fallback = []
    lstsq = implicit._adjoint_lstsq
    monkeypatch.setattr(implicit, "_adjoint_lstsq", lambda res, g, sel: fallback.append(sel) or lstsq(res, g, sel))
    gen = torch.Generator().manual_seed(301)
    random_instance(gen, 37, 1, 3)
    torch.rand(37, 1, generator=gen)
    data = random_instance(gen, 37, 1, 3, rank=1)
    active = torch.rand(37, 1, generator=gen) > 0.15

    def grads(sel):
        ins = [t[sel].clone().requires_grad_() for t in data]
        f = solve_cone_qp(*ins, active=active[sel], on_failure="count")
        (f * torch.linspace(-1, 1, 3, dtype=f.dtype)).pow(2).sum().backward()
        return [t.grad for t in ins]

    first = grads(slice(None))
    assert len(fallback) == 1 and fallback[0].sum() == 1
    b = int(fallback[0].nonzero()[0][0])
    for sel, row in ((slice(None), b), (slice(None), b), (slice(b, b + 1), 0)):
        for g0, g1 in zip(first, grads(sel)):
            assert torch.equal(g0[b], g1[row])


def test_the_adjoint_skips_a_failed_element_whose_unfinished_state_would_break_its_least_squares():
    # a failed solve (its impulses were set to 0) keeps the interior-point method's unfinished state; its K can be
    # anything, here non-finite, and LAPACK's SVD in the least-squares adjoint does not converge on it (a noisy Rope
    # training stopped so). The backward pass skips it: its gradient is that of a constant, 0.
    from diffcontact.solver.implicit import adjoint_solve
    from diffcontact.solver.kernel import IPMResult
    from diffcontact.solver.status import Status

    B, K, d = 2, 16, 1
    rng = np.random.default_rng(0)
    M = rng.standard_normal((B, K * d, K * d))
    A = np.ascontiguousarray(M @ np.swapaxes(M, 1, 2) + np.eye(K * d))
    A[1, 0, 0] = np.nan
    res = IPMResult(A, np.ones((B, K * d)), np.zeros((B, K), bool), np.ones((B, K), bool), d)
    res.status[1] = int(Status.NUMERICAL)
    g = rng.standard_normal((B, K * d))
    g[1] = 0.0
    try:  # (without the skip, the unfinished state's NaN reaches the gradient, or LAPACK raises on it)
        u, _ = adjoint_solve(res, g)
        assert not np.isfinite(u[1]).all()
    except np.linalg.LinAlgError:
        pass
    u, v = adjoint_solve(res, g, skip=res.status >= int(Status.MAX_ITER))
    assert not u[1].any() and not v[1].any() and np.isfinite(u[0]).all() and np.isfinite(v[0]).all()


def test_the_pseudo_inverse_of_a_kkt_matrix_on_which_lapacks_svd_fails(monkeypatch):
    # a finite KKT matrix of norm 1 from a noisy Rope training, on which numpy's SVD (LAPACK gesdd) did not converge
    # here; whether it does depends on the machine's LAPACK kernels, so the failure is forced
    from diffcontact.solver.implicit import pseudo_inverse

    K = np.load(Path(__file__).parent / "data" / "degenerate_kkt.npy")[None]  # (Kᵀ, as the adjoint inverts it)

    def fails(*args, **kwargs):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(np.linalg, "pinv", fails)
    P = pseudo_inverse(K)
    assert np.isfinite(P).all()
    scale = np.abs(K).max()
    assert np.abs(K @ P @ K - K).max() < 1e-6 * scale  # (the Moore-Penrose conditions, to the cut-off's accuracy)
    assert np.abs(P @ K @ P - P).max() < 1e-6 * np.abs(P).max()
    assert np.allclose(P @ K, np.swapaxes(P @ K, -1, -2), atol=1e-6) and np.allclose(
        K @ P, np.swapaxes(K @ P, -1, -2), atol=1e-6
    )
    regular = K + 0.5 * np.eye(K.shape[-1])  # (a regular matrix: the inverse, either way)
    assert np.allclose(pseudo_inverse(regular) @ regular, np.eye(K.shape[-1]), atol=1e-9)


def test_a_start_far_below_the_solution_is_not_taken_for_a_stall():
    # 52 bend and stretch limits in use on a rope of 50 nodes (frictionless, d = 1; a training batch of the
    # simulator's own states).  From the default start the gap grows for eight iterations while the infeasibility
    # falls: a stall rule on the residual alone ended the method at iteration 8 (MAX_ITER, residual 0.12), and so
    # did both retries.
    from solver_oracle import TOL_F, clarabel_solve

    from diffcontact.solver import solve_cone_qp

    data = np.load(Path(__file__).parent / "data" / "rope50_limits.npz")
    A, q = data["A"][None], data["q"][None]
    K = A.shape[-1]
    mu, lower, active = np.zeros((1, K)), np.zeros((1, K)), np.ones((1, K), dtype=bool)
    A_s, c, l_hat, T, *_, on_q, on_l, _ = scaling.scale_batch(A, q, mu, lower, active, contact_dims(1))
    trace = np.zeros((1, 61, 4))
    first = _iterates(A_s, T, c, l_hat, on_q, on_l, 1, trace)
    assert first.status.tolist() == [Status.CONVERGED] and first.iterations.item() <= 20
    gap = trace[0, : first.iterations.item(), 2]
    assert gap[8] > 2 * gap[1]  # (the case the rule must let pass: the gap rose from iteration 1 to 8)
    f, info = solve_cone_qp(torch.from_numpy(A), torch.from_numpy(q), torch.zeros(1, K), return_info=True)
    assert info.status.tolist() == [Status.CONVERGED]
    ref, _ = clarabel_solve(A[0], q[0], mu[0], lower[0], 1)
    assert np.abs(f[0].numpy() - ref).max() <= TOL_F * max(1.0, np.abs(ref).max())


def test_a_minimiser_on_the_edge_where_a_lower_bound_cuts_the_cone_is_polished_longer():
    """A restitution problem of the real cube with a learned e of 3e-7 (two corners of an edge, A singular): the
    first contact's minimiser sits where its lower bound e·f_n (8e-9, 1e-4 of the answer's size) meets its cone.
    The method stalls near 3e-7 and the usual polishing ends there (MAX_ITER, zero impulses); the last attempt's
    longer polishing reaches rounding, and the answer is Clarabel's."""
    from solver_oracle import clarabel_solve

    from diffcontact.solver import solve_cone_qp
    from diffcontact.solver.problem import POLISH_STEPS

    data = np.load(Path(__file__).parent / "data" / "lower_bound_edge.npz")
    A, q, mu, lower, active = (data[k][None] for k in ("A", "q", "mu", "lower", "active"))
    A_s, c, l_hat, T, *_, on_q, on_l, _ = scaling.scale_batch(A, q, mu, lower, active, contact_dims(3))
    options = dict(acceptable_tol=1e-7, max_iter=60, start_margin=START_MARGIN, refine_tol=IPM_TOL)
    usual = kernel.solve(A_s, T, c, l_hat, on_q, on_l, 3, ipm_tol=IPM_TOL, final_tol=1e-13, **options,
                         polish_steps=POLISH_STEPS)  # fmt: skip
    assert usual.status.tolist() == [Status.MAX_ITER]  # (the case the last attempt is for)
    given = [torch.from_numpy(a) for a in (A, q, mu, lower, active)]
    f, info = solve_cone_qp(*given, return_info=True)
    assert info.status.tolist() == [Status.CONVERGED]
    # (compared at the answer's own size: f = s·g with g of size 1, whose problem has q/s and lower/s; Clarabel's
    # absolute tolerances on the problem as given, whose answer is 4e-5, put its first normal impulse 1.8e-6 off)
    s = 1e-4
    g, A0, q0, mu0, lower0 = f[0].numpy() / s, A[0], q[0] / s, mu[0], lower[0] / s
    ref, obj = clarabel_solve(A0, q0, mu0, lower0, 3)
    grad = A0 @ g + q0  # (of size 5e3: the answer slides on both cones, held by the linear term)
    for k in range(2):  # feasible to rounding
        fn, ft = g[3 * k], g[3 * k + 1 : 3 * k + 3]
        assert fn >= lower0[k] * (1 - 1e-12) and np.linalg.norm(ft) <= mu0[k] * fn * (1 + 1e-12)
    ours = 0.5 * g @ A0 @ g + q0 @ g
    assert ours <= obj + 1e-10 * np.abs(grad).max()  # (no worse than Clarabel's: 6e-12 lower, in fact)
    # both slide: −g_t along f_t, and g_n = μ‖g_t‖ at the second (the first also holds its bound, g_n > μ‖g_t‖)
    for k in range(2):
        gt, ft = grad[3 * k + 1 : 3 * k + 3], g[3 * k + 1 : 3 * k + 3]
        assert np.linalg.norm(gt / np.linalg.norm(gt) + ft / np.linalg.norm(ft)) <= 1e-8
    assert abs(grad[3] - mu0[1] * np.linalg.norm(grad[4:6])) <= 1e-9 * np.abs(grad).max()
    # (the answer's sensitivity to the conditions: Clarabel's, 100 times nearer the last one, differs by 7e-7)
    assert np.abs(g - ref).max() <= 1e-6 * np.abs(ref).max()
    f = f[0].numpy()
    assert f[0] == pytest.approx(lower[0, 0], rel=1e-6)  # (on the edge: the bound and the cone both hold tight)
    assert np.linalg.norm(f[1:3]) == pytest.approx(mu[0, 0] * f[0], rel=1e-6)
    # with gradients (the training's path: the minimiser is solved again, centred, and differentiated)
    A_t = given[0].clone().requires_grad_(True)
    f_g, info = solve_cone_qp(A_t, *given[1:], return_info=True)
    assert info.status.tolist() == [Status.CONVERGED] and np.abs(f_g[0].detach().numpy() - f).max() <= 1e-12
    f_g.sum().backward()
    assert A_t.grad is not None and torch.isfinite(A_t.grad).all()
