"""The failure policy and counters of ContactSolver, through the whole solver path (retries included).

A failing kernel status is forced on one batch element by wrapping the compiled kernel's ``kernel.solve`` (the
well-posed problems of the simulation do not fail, so a genuine MAX_ITER or NUMERICAL cannot be made on demand);
everything from the retry policy to the autograd Function then runs as it does in the simulation.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from diffcontact.errors import ContactSolverError
from diffcontact.solver import ContactSolver, Status, kernel

F64 = torch.float64


def _problems(B: int = 5, K: int = 3, d: int = 2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(3)
    L = torch.randn(B, K * d, K * d, generator=gen, dtype=F64)
    A = L @ L.mT + 0.1 * torch.eye(K * d, dtype=F64)
    return A, torch.randn(B, K * d, generator=gen, dtype=F64), torch.rand(B, K, generator=gen, dtype=F64)


@pytest.fixture
def fail_element_1(monkeypatch):
    """Force the kernel's status ``code`` on batch element 1 in every attempt, once the test sets ``code`` (with the
    residual of a failure, inf, as the kernel would pair them)."""
    real, forced = kernel.solve, {}

    def solve(*args, out=None, **kw):
        res = real(*args, out=out, **kw)
        if "code" in forced:
            res.status[1] = forced["code"]
            res.residual[1] = np.inf
        return res

    monkeypatch.setattr(kernel, "solve", solve)
    return forced


@pytest.mark.parametrize("code", [Status.MAX_ITER, Status.NUMERICAL])
def test_contact_solver_raises_on_a_failed_element_by_default(fail_element_1, code):
    fail_element_1["code"] = code
    solver = ContactSolver()
    with pytest.raises(ContactSolverError, match=rf"1 of 5 batch elements \[1\].*{code.name}") as err:
        solver(*_problems())
    assert err.value.failed == [1]


@pytest.mark.parametrize("code", [Status.MAX_ITER, Status.NUMERICAL])
def test_contact_solver_counts_failures_and_returns_zero_impulses_for_them(fail_element_1, code):
    A, q, mu = _problems()
    expected = ContactSolver()(A, q, mu)  # (nothing forced yet)
    fail_element_1["code"] = code
    solver = ContactSolver(on_failure="count")
    for _ in range(2):
        f = solver(A, q, mu)
    assert torch.equal(f[1], torch.zeros_like(f[1]))
    keep = torch.tensor([0, 2, 3, 4])
    assert torch.equal(f[keep], expected[keep])
    assert solver.calls == 2 and solver.problems == 10
    assert solver.failures_by_status == {code.name: 2} and solver.failures == 2
    solver.reset()
    assert solver.calls == solver.problems == solver.failures == 0


def test_contact_solver_keeps_the_first_failed_problems_as_given_and_they_solve_again(fail_element_1, tmp_path):
    """With ``keep`` the first failed problems are kept as they were given (dtype included), written and read back
    by ``save_failed`` / ``load_failed`` bit for bit, and solve again from the file (here, with the forced failure
    gone, to the answer of the whole batch)."""
    from diffcontact.solver import solve_cone_qp
    from diffcontact.solver.contact_solver import load_failed, save_failed

    A, q, mu = (t.float() for t in _problems())
    lower = torch.zeros_like(mu)
    expected = ContactSolver()(A, q, mu, lower)
    fail_element_1["code"] = Status.NUMERICAL
    solver = ContactSolver(on_failure="count", keep=1)
    for _ in range(2):
        solver(A, q, mu, lower)
    assert solver.failures == 2 and len(solver.failed) == 1  # (the second failure is counted, not kept)
    kept = solver.failed[0]
    assert set(kept) == {"A", "q", "mu", "lower", "status", "index", "batch_A", "batch_q", "batch_mu", "batch_lower"}
    assert int(kept["status"]) == Status.NUMERICAL and int(kept["index"]) == 1
    assert np.array_equal(kept["batch_A"], A.numpy()) and np.array_equal(kept["batch_mu"], mu.numpy())
    assert kept["A"].dtype == np.float32 and np.array_equal(kept["A"], A[1].numpy())
    assert np.array_equal(kept["q"], q[1].numpy()) and np.array_equal(kept["mu"], mu[1].numpy())
    back = load_failed(save_failed(tmp_path / "failed.npz", solver.failed))
    assert len(back) == 1 and all(np.array_equal(back[0][k], kept[k]) for k in kept)
    fail_element_1.clear()
    f = solve_cone_qp(*(torch.from_numpy(back[0][k])[None] for k in ("A", "q", "mu", "lower")))
    assert torch.equal(f[0], expected[1])
    solver.reset()
    assert solver.failed == [] and solver.failures == 0


def test_contact_solver_passes_its_options_and_rejects_an_unknown_policy():
    A, q, mu = _problems()
    seen = {}

    def spy(*args, **kw):
        seen.update(kw)
        return ContactSolver().backend(*args, **kw)

    ContactSolver(tol=1e-8, acceptable_tol=1e-6, max_iter=7, backend=spy)(A, q, mu)
    assert {k: seen[k] for k in ("tol", "acceptable_tol", "max_iter", "on_failure")} == {
        "tol": 1e-8,
        "acceptable_tol": 1e-6,
        "max_iter": 7,
        "on_failure": "raise",
    }
    with pytest.raises(ValueError, match=r"on_failure must be one of \['raise', 'count'\], got 'ignore'"):
        ContactSolver(on_failure="ignore")


def test_every_threshold_is_the_policys_and_docs_solver_md_lists_them_all():
    import re
    from pathlib import Path

    from diffcontact.contact import impulse
    from diffcontact.solver import contact_solver, least_norm, optimality, problem, scaling, status
    from diffcontact.solver.policy import POLICY

    bound = {
        (problem, "IPM_TOL"): "ipm_tol", (problem, "ROUNDING_TOL"): "rounding_tol", (problem, "POLISH_STEPS"):
        "polish_steps", (problem, "POLISH_RETRY_STEPS"): "polish_retry_steps",
        (problem, "START_MARGIN"): "start_margin", (problem, "ROBUST_MARGIN"): "robust_margin",
        (problem, "FAR"): "far", (problem, "TIKHONOV"): "tikhonov",
        (problem, "TIKHONOV_MAX"): "tikhonov_max", (problem, "MU_CAP"): "mu_cap",
        (problem, "MU_MAX"): "mu_max", (least_norm, "Q_TOL"): "q_tol", (least_norm, "UNIQUE_TOL"): "unique_tol",
        (least_norm, "RHO"): "alm_rho", (least_norm, "RHO_MAX"): "alm_rho_max", (least_norm, "ALM_STEPS"): "alm_steps",
        (least_norm, "ALM_TOL"): "alm_tol", (least_norm, "ALM_ACCEPT"): "alm_accept",
        (least_norm, "ALM_FLOOR"): "alm_floor",
        (least_norm, "ALM_FAR"): "alm_far", (least_norm, "V_ROUNDING"): "v_rounding", (least_norm, "PROX"): "prox",
        (optimality, "MU_CHECKED"): "mu_checked", (scaling, "MU_FREE"): "mu_free", (status, "WEAK_TOL"): "weak_tol",
        (impulse, "FLAT_TOL"): "wide_flat_tol",
    }  # fmt: skip
    for (module, name), field in bound.items():
        assert getattr(module, name) == getattr(POLICY, field), name
    defaults = contact_solver.ContactSolver()
    assert (defaults.tol, defaults.acceptable_tol, defaults.max_iter) == (POLICY.tol, POLICY.acceptable_tol, 60)
    docs = (Path(__file__).parents[1] / "docs" / "solver.md").read_text()
    listed = dict(re.findall(r"^\| `(\w+)` \| ([^|]+) \|", docs, flags=re.M))
    assert listed == {name: f"{value:g}" for name, value in POLICY.table()}
