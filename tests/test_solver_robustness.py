"""Degenerate and invalid inputs: the solver reports status, raises clear errors, and never returns NaN."""

from __future__ import annotations

import pytest
import torch

from diffcontact.errors import ContactSolverError
from diffcontact.solver import Status, solve_cone_qp


def _degenerate_batch(gen: torch.Generator, B: int, K: int, d: int) -> tuple:
    """Zero rows, μ = 0, rank-deficient A, scales 1e-6 … 1e6, inactive contacts, all mixed."""
    n = K * d
    r = torch.randint(1, n + 1, (B,), generator=gen)
    M = torch.randn(B, n, n, generator=gen, dtype=torch.float64)
    M = M * (torch.arange(n)[None, None, :] < r[:, None, None])  # rank r
    zero = torch.rand(B, K, generator=gen) < 0.15  # zero rows/columns of A for these contacts
    M = M * (~zero).repeat_interleave(d, -1)[..., None]
    scale = 10.0 ** torch.empty(B, 1, 1, dtype=torch.float64).uniform_(-6, 6, generator=gen)
    A = scale * M @ M.mT
    u = torch.randn(B, n, 1, generator=gen, dtype=torch.float64)
    q = (scale * M @ u)[..., 0]  # in the range of A: bounded problems
    # contacts with a zero row get a separating normal velocity and no tangential one (q in the dual cone, so
    # the problem stays bounded)
    normal = torch.zeros(K, d, dtype=torch.float64)
    normal[:, 0] = 1.0
    push = 0.5 * scale[..., 0] * torch.rand(B, n, generator=gen, dtype=torch.float64) * normal.view(1, n)
    q = q + zero.repeat_interleave(d, -1) * push
    mu = torch.rand(B, K, generator=gen, dtype=torch.float64) * (torch.rand(B, K, generator=gen) > 0.4)
    lower = (
        scale[..., 0] * torch.rand(B, K, generator=gen, dtype=torch.float64) * (torch.rand(B, K, generator=gen) > 0.6)
    )
    lower = lower * ~zero
    active = torch.rand(B, K, generator=gen) > 0.2
    active[: B // 10] = False  # some elements with every contact inactive
    return A, q, mu, lower, active


@pytest.mark.parametrize("K,d", [(1, 1), (3, 2), (5, 3), (19, 1)])
def test_fuzz_degenerate_inputs_never_nan_and_always_report(K, d):
    gen = torch.Generator().manual_seed(100 + 10 * K + d)
    A, q, mu, lower, active = _degenerate_batch(gen, 200, K, d)
    f, info = solve_cone_qp(A, q, mu, lower, active, on_failure="count", return_info=True)
    assert torch.isfinite(f).all()
    assert info.status.shape == (200,)
    assert ((info.status >= 0) & (info.status <= Status.UNBOUNDED)).all()
    assert (f[info.failed] == 0).all()
    assert (f[~active.repeat_interleave(d, -1)] == 0).all()
    assert (f[:20] == 0).all() and (info.status[:20] == Status.CONVERGED).all()
    # the solutions that are reported usable are feasible
    fk = f.view(200, K, d)
    ok = ~info.failed[:, None] & active
    assert (fk[..., 0][ok] >= lower[ok] * (1 - 1e-9) - 1e-12 * lower.abs().amax()).all()
    if d > 1:
        slack = mu * fk[..., 0] - fk[..., 1:].norm(dim=-1)
        assert (slack[ok] >= -1e-8 * fk.abs().amax()).all()
    assert info.n_failed <= 2  # bounded, well-posed problems: failures are rare and reported


def test_least_norm_stage_stalled_at_its_inner_accuracy_takes_its_iterate_finished_by_a_proximal_step(monkeypatch):
    """Element 167 of a degenerate batch (K = 19, d = 1): A has two flat directions and entries up to 1.5e7.  The
    least-norm stage's augmented Lagrangian stalls at a miss of about 5e-8 of its scale (the inner solves' accuracy),
    3.8e5 away from its start: its last iterate is the least-norm minimiser up to that (it used to keep its start, a
    minimiser 9 % larger in norm, with status 0; then the iterate itself, INACCURATE), finished by
    the proximal step into a minimiser, CONVERGED (the miss is below ALM_FLOOR).  Reference: the same stage
    converged from the interior-point method run to 1e-7 (no independent solver accepts the instance at these
    scales)."""
    from diffcontact.solver import problem

    A, q, mu, lower, active = _degenerate_batch(torch.Generator().manual_seed(291), 200, 19, 1)
    one = slice(167, 168)
    f, info = solve_cone_qp(A[one], q[one], mu[one], lower[one], active=active[one], return_info=True)
    monkeypatch.setattr(problem, "IPM_TOL", 1e-7)
    ref, ref_info = solve_cone_qp(A[one], q[one], mu[one], lower[one], active=active[one], return_info=True)
    assert ref_info.status.tolist() == [Status.CONVERGED]
    assert info.status.tolist() == [Status.CONVERGED]

    def objective(x):
        return 0.5 * x @ A[167] @ x + q[167] @ x

    assert torch.isclose(objective(f[0]), objective(ref[0]), rtol=1e-7)
    assert torch.isclose(f.norm(), ref.norm(), rtol=1e-7)  # (its start: 1.36e6 against 1.25e6)


def test_gradients_are_finite_on_degenerate_inputs():
    gen = torch.Generator().manual_seed(7)
    A, q, mu, lower, active = _degenerate_batch(gen, 64, 3, 3)
    ins = [t.clone().requires_grad_() for t in (A, q, mu, lower)]
    f = solve_cone_qp(*ins, active, on_failure="count")
    f.sum().backward()
    for t in ins:
        assert torch.isfinite(t.grad).all()


def test_unbounded_problem_raises_with_the_failing_elements():
    A = torch.zeros(2, 1, 1, dtype=torch.float64)
    q = torch.tensor([[1.0], [-1.0]], dtype=torch.float64)  # element 1: f_n → ∞ lowers the objective forever
    with pytest.raises(ContactSolverError, match=r"failed for 1 of 2 batch elements \[1\].*UNBOUNDED"):
        solve_cone_qp(A, q, torch.zeros(2, 1, dtype=torch.float64))
    f, info = solve_cone_qp(A, q, torch.zeros(2, 1, dtype=torch.float64), on_failure="count", return_info=True)
    assert info.status.tolist() == [Status.CONVERGED, Status.UNBOUNDED]
    assert f[1].item() == 0.0 and info.n_failed == 1


@pytest.mark.parametrize(
    "field,kwargs,match",
    [
        ("A", {"A": torch.full((1, 2, 2), float("nan"), dtype=torch.float64)}, "A has non-finite values"),
        ("q", {"q": torch.tensor([[float("inf"), 0.0]], dtype=torch.float64)}, "q has non-finite values"),
        ("mu", {"mu": torch.tensor([[-0.1]], dtype=torch.float64)}, "mu must be >= 0"),
        ("lower", {"lower": torch.tensor([[-1.0]], dtype=torch.float64)}, "lower must be >= 0"),
        ("shape", {"q": torch.zeros(1, 3, dtype=torch.float64)}, r"q must have shape"),
        ("dim", {"mu": torch.zeros(1, 3, dtype=torch.float64)}, "contact dimension"),
        ("active", {"active": torch.ones(1, 1)}, "active must be a bool tensor"),
    ],
)
def test_bad_input_gives_one_clear_error(field, kwargs, match):
    args = {
        "A": torch.eye(2, dtype=torch.float64)[None],
        "q": torch.tensor([[-1.0, 0.5]], dtype=torch.float64),
        "mu": torch.tensor([[0.5]], dtype=torch.float64),
    }
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        solve_cone_qp(**args)
