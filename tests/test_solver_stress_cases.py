"""The silent failures an earlier contact-solver stress run found (``benchmarks/bench_solver_stress.py --total
1000000``, seed 0): usable answers with μ ≤ 1.5 that were wrong.  Each problem is the one the run drew (call and
element as the script prints them; ``--calls N`` replays a call), written out here.

- ``infinite_mass`` (A = 0), calls 191, 400, 697: unbounded problems (q outside the dual cone of some contact)
  reported CONVERGED with an impulse of 1e-5 … 1e-4.  The retry that re-solves a stalled element with γ set to
  the size of its iterate took the size of an iterate running away along the unbounded ray (1e11): the scaled
  linear term fell to 1e-12, below the kernel's tolerance (absolute where ‖z‖∞ < 1), and noise near z = 0 passed.
- ``singular`` (rank 1, q in the range), call 849: the minimisers form an unbounded set along the normal direction;
  the first solve ended 2e7 times farther out than the least-norm point and the move back left a 4 % error.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch
from solver_oracle import clarabel_min_norm, clarabel_solve

from diffcontact.solver import Status, solve_cone_qp

_spec = importlib.util.spec_from_file_location(
    "bench_solver_stress", Path(__file__).parents[1] / "benchmarks" / "bench_solver_stress.py"
)
stress = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(stress)

# (q, μ) of the A = 0 problems, d = 3: calls 191 (element 903, K = 2), 400 (153) and 697 (230)
UNBOUNDED = [
    (
        [0.8416253182274797, -0.26153685207398714, -2.2124880413431933, 1.4633935156214963, -0.9138335426753612,
         -0.5913783319422257],
        [0.8075878474755949, 1.0101578706156082],
    ),
    ([1.1607644798128, -0.3759437128843198, 1.3511703271364461, 0.0, 0.0, 0.0], [1.1743278760359317, 1.0]),
    ([0.7085935118493044, 1.335512195665043, -0.47785632011025725, 0.0, 0.0, 0.0], [0.6658324921725263, 1.0]),
]  # fmt: skip
# call 849, element 736 (d = 2): the A given (PSD up to a −2.8e-10 eigenvalue) and the exact rank-1 A
SINGULAR_A = [[7.210660044658479e-10, -1.6602736782179214e-05], [-1.6602736782179214e-05, 0.27636174088096793]]
SINGULAR_EXACT = [[9.974277453468159e-10, -1.6602736765576477e-05], [-1.6602736765576473e-05, 0.27636174088096793]]
SINGULAR_Q = [5.612862545267215e-06, -0.09342920304270501]
SINGULAR_MU = [0.8541244766410516]


def test_zero_mass_problems_outside_the_dual_cone_fail_and_inside_converge_to_zero():
    """A = 0: the problem min qᵀf over the cones is unbounded where some contact has q_n < μ‖q_t‖ (the ray
    f = (1, −μ q_t/‖q_t‖) lowers it without limit), else f = 0 is the minimiser."""
    q = torch.tensor([u[0] for u in UNBOUNDED] + [[1.0, 0.1, -0.2, 2.0, 0.5, 0.5]], dtype=torch.float64)
    mu = torch.tensor([u[1] for u in UNBOUNDED] + [[1.5, 1.0]], dtype=torch.float64)
    qk = q.view(4, 2, 3)
    unbounded = (qk[..., 0] < mu * qk[..., 1:].norm(dim=-1)).any(-1)
    assert unbounded.tolist() == [True, True, True, False]  # (the independent classification)
    f, info = solve_cone_qp(torch.zeros(4, 6, 6, dtype=torch.float64), q, mu, on_failure="count", return_info=True)
    assert info.failed.tolist() == [True, True, True, False], info.status
    assert info.status[3] == Status.CONVERGED
    assert (f[:3] == 0).all()  # (failed: zeros)
    assert f[3].abs().max() < 1e-12  # (the minimiser 0)


def test_an_unbounded_set_of_minimisers_along_the_normal_gives_the_least_norm_one():
    A = torch.tensor([SINGULAR_A], dtype=torch.float64)
    q = torch.tensor([SINGULAR_Q], dtype=torch.float64)
    mu = torch.tensor([SINGULAR_MU], dtype=torch.float64)
    exact = np.array(SINGULAR_EXACT)
    f_opt, _ = clarabel_solve(exact, q[0].numpy(), mu[0].numpy(), np.zeros(1), 2)
    reference = clarabel_min_norm(exact, q[0].numpy(), mu[0].numpy(), np.zeros(1), 2, f_opt)
    # in closed form: A = λ u uᵀ, q = κ u, so the minimisers are the f in the cone with u·f = s = −κ/λ; the point
    # s·u of least norm on that line is outside the cone, so the least-norm minimiser is on its boundary,
    # f = (f_n, ±μ f_n) with f_t of the sign of s·u_t
    lam, V = np.linalg.eigh(exact)
    u, kappa = V[:, 1], V[:, 1] @ q[0].numpy()
    s = -kappa / lam[1]
    assert abs(s * u[1]) > SINGULAR_MU[0] * s * u[0]  # (s·u outside the cone)
    sign = np.sign(s * u[1])
    fn = s / (u[0] + sign * SINGULAR_MU[0] * u[1])
    closed = np.array([fn, sign * SINGULAR_MU[0] * fn])
    np.testing.assert_allclose(reference, closed, rtol=1e-7)
    for grad in (False, True):  # (with a gradient the path is another: centred on a minimiser inside the set)
        qq = q.clone().requires_grad_(grad)
        f, info = solve_cone_qp(A, qq, mu, on_failure="count", return_info=True)
        assert info.status[0] == Status.CONVERGED
        np.testing.assert_allclose(f.detach()[0].numpy(), closed, rtol=1e-8)  # (TOL_F: A is perturbed)
        res = stress.residual(
            exact[None], q.numpy(), mu.numpy(), np.zeros((1, 1)), np.ones((1, 1), bool), f.detach().numpy(), 2
        )
        assert res[0] < 1e-9
        if grad:
            (g,) = torch.autograd.grad(f.sum(), qq)
            assert torch.isfinite(g).all()


@pytest.mark.parametrize("kind", ["singular", "infinite_mass"])
def test_stress_kinds_have_no_silent_failure_on_a_small_batch(kind):
    """Two thousand problems of the kinds that had them, the script's own independent check."""
    rng = np.random.default_rng(1)
    silent = 0
    for K, d in ((1, 2), (1, 3), (2, 3), (3, 2)):
        A, exact, q, mu, lower, active = stress.instance(rng, kind, 500, K, d)
        f, info = solve_cone_qp(
            *(torch.from_numpy(a) for a in (A, q, mu, lower)), torch.from_numpy(active), on_failure="count",
            return_info=True,
        )  # fmt: skip
        usable = ~info.failed.numpy()
        res = stress.residual(exact, q, mu, lower, active, f.numpy(), d)
        silent += int((res[usable] > stress.TOL[torch.float64]).sum()) + int((f.numpy()[~usable] != 0).sum())
    assert silent == 0
