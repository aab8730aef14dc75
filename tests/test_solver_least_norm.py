"""Effective-mass matrices that are PSD up to rounding, and minimisers that are not unique (solver/least_norm.py).

Every contact dimension and size the 8 benchmark tasks use: d = 1 with up to 19 contacts (rope), d = 2 with up to
5 (balls, pendulum, disks), d = 3 with 1 (gyroscope).  A is singular PSD, rounded to float32 and perturbed by
±1e-7·‖A‖ in its null space; q lies in the range of A, as J v does for a velocity v that obeys the joints.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from solver_oracle import TOL_OBJ, clarabel_min_norm, clarabel_solve, kkt_residual

from diffcontact.bench.near_psd import TASK_SIZES, near_psd_instance
from diffcontact.errors import IndefiniteMatrixError
from diffcontact.solver import Status, solve_cone_qp
from diffcontact.solver.optimality import natural_residual

# The gyroscope problem of the issue: a 3×3 A (float32 in training) with eigenvalues −6.7e-8, 0.1005, 0.1052;
# minimisers form a segment along the null direction, the line from the rim contact to the pivot.
GYRO_A = [
    [0.0663641020655632, -0.04685269668698311, -0.010782204568386078],
    [-0.04685269668698311, 0.03714560344815254, -0.012602319940924644],
    [-0.010782204568386078, -0.012602319940924644, 0.10220163315534592],
]
GYRO_Q = [-1.815451979637146, 0.6259483098983765, 3.5535082817077637]
GYRO_MU = [1.1851791143417358]

TOL_F = 1e-6  # against the two-stage Clarabel reference (its own errors reach a few 1e-7 at 1e-10 tolerance)


def _projected(A: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The problem as the solver states it (solver/least_norm.py), computed independently: eigenvalues of magnitude
    ≤ 1e-6·s set to 0 (the PSD projection, and a rounding-level positive eigenvalue counted as 0), and q's component
    along them (rounding: q = F w) removed; s, an eigenvector v's scale: (Σ |v_i| √A_ii)², between 0.01·max(diag A)
    and max(diag A)."""
    evals, V = np.linalg.eigh(0.5 * (A + A.T))
    top = np.diag(A).max()
    scale = np.clip((np.abs(V) * np.sqrt(np.maximum(np.diag(A), 0.0))[:, None]).sum(0) ** 2, 0.01 * top, top)
    flat = np.abs(evals) <= 1e-6 * scale
    VN = V[:, flat]
    return (V * np.where(flat, 0.0, evals)) @ V.T, q - VN @ (VN.T @ q)


@pytest.mark.parametrize("K,d", TASK_SIZES)
def test_near_psd_problems_converge_to_the_minimum_norm_minimiser(K, d):
    """float64: against Clarabel on the PSD projection (objective, KKT conditions, minimum-norm minimiser);
    float32 in and out: the float64 solution rounded (the solver works in float64 either way)."""
    gen = torch.Generator().manual_seed(10 * K + d)
    B = 12
    A, q, mu, lower, _, _ = near_psd_instance(gen, B, K, d)
    f, info = solve_cone_qp(A.double(), q.double(), mu.double(), lower.double(), return_info=True)
    f32, info32 = solve_cone_qp(A, q, mu, lower, return_info=True)
    assert (info.status == Status.CONVERGED).all() and (info32.status == Status.CONVERGED).all()
    assert f32.dtype == torch.float32
    # (float32 counts eigenvalues up to 1.2e-5·ref as flat, float64 up to 1e-6: the two stated problems can differ
    # by that much; the objective is compared below)
    for b in range(B):
        Ab, qb = _projected(A[b].double().numpy(), q[b].double().numpy())
        mub, lb = (t[b].double().numpy() for t in (mu, lower))
        f_ref, obj_ref = clarabel_solve(Ab, qb, mub, lb, d)
        fb = f[b].numpy()
        obj = 0.5 * fb @ Ab @ fb + qb @ fb
        scale = max(1.0, np.abs(f_ref).max())
        obj_scale = max(1.0, abs(obj_ref), np.abs(qb).max() * scale)
        assert abs(obj - obj_ref) <= TOL_OBJ * obj_scale, (b, obj, obj_ref)
        f32b = f32[b].double().numpy()
        assert abs(0.5 * f32b @ Ab @ f32b + qb @ f32b - obj_ref) <= 1e-5 * obj_scale, b
        assert kkt_residual(Ab, qb, mub, lb, fb, d) <= 1e-8, b
        f_min = clarabel_min_norm(Ab, qb, mub, lb, d, f_ref)
        # (Clarabel's own errors along a cone's boundary reach a few 1e-6: tests/test_solver_accuracy.py)
        tol_f = TOL_F + 10 * max(kkt_residual(Ab, qb, mub, lb, f_ref, d), kkt_residual(Ab, qb, mub, lb, f_min, d))
        # a minimiser (KKT above) whose norm is not above the least one is the minimum-norm minimiser (the norm is
        # strictly convex); compared by norm, as Clarabel's two-stage point is inaccurate along a flat direction
        # tangent to a cone (a sliding contact, where the minimiser is unique: error ~ sqrt of its residual)
        gap = tol_f
        slack = np.sqrt(kkt_residual(Ab, qb, mub, lb, f_min, d))  # (its displacement along a tangent line)
        assert np.linalg.norm(fb) <= np.linalg.norm(f_min) * (1 + gap + slack) + tol_f, (b, fb, f_min)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gyroscope_problem_of_the_issue(dtype):
    A, q, mu = (torch.tensor(x, dtype=torch.float64) for x in (GYRO_A, GYRO_Q, GYRO_MU))
    f, info = solve_cone_qp(A[None].to(dtype), q[None].to(dtype), mu[None].to(dtype), return_info=True)
    assert info.status.item() == Status.CONVERGED
    Ap, qp = _projected(A.numpy(), q.numpy())
    zero = np.zeros(1)
    f_ref, obj_ref = clarabel_solve(Ap, qp, mu.numpy(), zero, 3)
    f_min = clarabel_min_norm(Ap, qp, mu.numpy(), zero, 3, f_ref)
    fb = f[0].double().numpy()
    assert abs(0.5 * fb @ Ap @ fb + qp @ fb - obj_ref) <= TOL_OBJ * abs(obj_ref)
    rel = 1e-6 if dtype == torch.float64 else 1e-6 + 4 * torch.finfo(dtype).eps
    assert np.abs(fb - f_min).max() <= rel * np.abs(f_min).max(), (fb, f_min)
    # the velocity change is the one of every minimiser; the impulse is the smallest (Clarabel's own, any point of
    # the segment, was (176, 208, 9.5) in the issue)
    assert np.abs(Ap @ (fb - f_ref)).max() <= 1e-6 * np.abs(q.numpy()).max()
    assert np.linalg.norm(fb) <= np.linalg.norm(f_ref) * (1 + 1e-9)


@pytest.mark.parametrize(
    "K,d,mu_scale,seed",
    [
        (1, 3, 3.0, 0),
        (1, 3, 0.5, 1),
        (2, 2, 1.0, 2),
        (2, 2, 2.0, 5),
        (3, 1, 1.0, 3),
        # several flat directions and a set of minimisers (the augmented Lagrangian stage): nullity 2, 3 and 2
        (2, 3, 1.0, 8),
        (5, 2, 1.0, 10),
        (6, 1, 1.0, 8),
    ],
)
@pytest.mark.slow
def test_gradcheck_through_a_singular_effective_mass(K, d, mu_scale, seed):
    """A = F Fᵀ + rounding and q = F w, as A = J M⁻¹ Jᵀ and q = J v are formed: the finite differences move the
    null space of A and q with it (perturbing A alone would leave q with a component the joints do not allow)."""
    gen = torch.Generator().manual_seed(seed)
    B = 4
    A32, _, mu, lower, F, w = near_psd_instance(gen, B, K, d, mu_scale)
    E = A32.double() - F @ F.mT  # the rounding, held fixed

    def fn(F, w, mu, lower):
        return solve_cone_qp(F @ F.mT + E, (F @ w[..., None])[..., 0], mu, lower)

    lower = lower + 0.05  # (> 0: the finite differences stay feasible)
    inputs = tuple(t.double().clone().requires_grad_() for t in (F, w, mu, lower))
    # (eps 1e-5: the forward solves of a near-singular A carry rounding noise of ~1.5e-11, which a difference
    # quotient at eps 1e-6 magnifies to ~1e-5, the tolerance itself)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-5, atol=1e-5, rtol=1e-4)


def test_a_push_along_a_flat_direction_in_the_cone():
    """A flat direction inside the cone (here the normal: A = diag(0, 1, 1)) that q pushes along: a velocity that
    violates the joints is unbounded, or bounded where it pushes out of the cone; a drift (≤ 10 % of q) is
    dropped and the minimum-norm minimiser returned."""
    A = torch.diag(torch.tensor([0.0, 1.0, 1.0], dtype=torch.float64)).expand(4, 3, 3).clone()
    q = torch.tensor([[-1.0, 0.2, 0.0], [1.0, 0.2, 0.0], [-1e-9, 0.2, 0.0], [-0.01, 0.2, 0.0]], dtype=torch.float64)
    mu = torch.full((4, 1), 0.5, dtype=torch.float64)
    f, info = solve_cone_qp(A, q, mu, on_failure="count", return_info=True)
    assert info.status.tolist() == [Status.UNBOUNDED] + [Status.CONVERGED] * 3
    # bounded: q pushes out of the cone along the flat direction (friction would save less than the push costs)
    assert torch.allclose(f[1], torch.zeros(3, dtype=torch.float64), atol=1e-9)
    # drift, dropped: the minimum-norm minimiser, just enough normal impulse to stop the sliding
    least = torch.tensor([0.4, -0.2, 0.0], dtype=torch.float64)
    assert torch.allclose(f[2], least, atol=1e-9) and torch.allclose(f[3], least, atol=1e-9)


def test_a_set_of_minimisers_that_is_a_point_stops_the_augmented_lagrangian_early(monkeypatch):
    """A ball in a corner (a point mass, inverse mass 0.94, walls along x and y, μ = 1e-3: a problem met in BP5's
    training): A = m⁻¹·[[1,0,0,−1],[0,1,1,0],[0,1,1,0],[−1,0,0,1]] has two flat directions, yet the cones admit a
    single minimiser, f = (0, 0, s, μs) with s = (0.97 + 0.93μ) / (0.94(1 + μ²)) (minimise over u = f₁ₙ − f₂ₜ ≥ −μf₂ₙ
    and s = f₁ₜ + f₂ₙ).  The augmented Lagrangian's miss then falls sublinearly; it stops once that is clear."""
    import diffcontact.solver.least_norm as flat

    solves = []
    several = flat._least_norm_several

    def counted(idx, x, PiN, solve, *problem):
        def counting(*args):
            solves.append(1)
            return solve(*args)

        return several(idx, x, PiN, counting, *problem)

    monkeypatch.setattr(flat, "_least_norm_several", counted)
    mu = 1e-3
    P = torch.tensor([[1.0, 0, 0, -1], [0, 1, 1, 0], [0, 1, 1, 0], [-1, 0, 0, 1]], dtype=torch.float64)
    q = torch.tensor([0.93, -0.97, -0.97, -0.93], dtype=torch.float64)
    mus = torch.full((1, 2), mu, dtype=torch.float64)
    f, info = solve_cone_qp((0.94 * P)[None], q[None], mus, return_info=True)
    s = (0.97 + 0.93 * mu) / (0.94 * (1 + mu**2))
    assert info.status.item() == Status.CONVERGED
    assert torch.allclose(f[0], torch.tensor([0.0, 0.0, s, mu * s], dtype=torch.float64), rtol=0, atol=1e-9)
    assert 0 < len(solves) <= 6 < flat.ALM_STEPS  # (20 solves before the stop)


def test_genuinely_indefinite_matrix_is_an_input_error():
    A = torch.eye(2, dtype=torch.float64).repeat(3, 1, 1)
    A[1, 1, 1] = -1e-3
    with pytest.raises(IndefiniteMatrixError, match=r"not positive semidefinite in batch elements \[1\]"):
        solve_cone_qp(A, torch.zeros(3, 2, dtype=torch.float64), torch.ones(3, 1, dtype=torch.float64))


def test_gyroscope_with_a_wide_friction_cone_simulates_without_failure():
    """μ = 1.2 puts the line from the rim contact to the pivot (the flat direction) inside the friction cone; the
    integrator's drift of the joint velocities (up to 2e-2 of q) is dropped instead of making the problem
    unbounded (with the drift kept, this raised UNBOUNDED)."""
    import dataclasses

    from diffcontact import build_task, simulator_for

    task = build_task("Gyro")
    params = dataclasses.replace(task.params, mu=torch.full_like(task.params.mu, 1.2))
    xs, vs, contact = simulator_for(task).rollout(task.sample(32, seed=0), params, task.dt, 100)
    assert contact.any() and torch.isfinite(xs).all() and torch.isfinite(vs).all()


@pytest.mark.parametrize("K,d", [(19, 1), (2, 3), (5, 2)])
def test_an_elements_solution_and_gradient_do_not_depend_on_its_batch(K, d):
    """The flat stage treats every element on its own (its flat directions, its least-norm steps)."""
    gen = torch.Generator().manual_seed(3 + K)
    A, q, mu, lower, _, _ = near_psd_instance(gen, 40, K, d)

    def solve(sl):
        ins = [t[sl].double().clone().requires_grad_() for t in (A, q, mu, lower)]
        f = solve_cone_qp(*ins)
        (f * torch.linspace(0.5, 1.5, f.shape[-1], dtype=torch.float64)).sum().backward()
        return f.detach(), [t.grad for t in ins]

    f_all, g_all = solve(slice(None))
    # without gradients the solver takes a shorter path (no second, centred solve): the same minimisers
    f_plain = solve_cone_qp(*(t.double() for t in (A, q, mu, lower)))
    assert torch.allclose(f_plain, f_all, rtol=1e-8, atol=1e-10)
    for b in (0, 7, 39):
        f_one, g_one = solve(slice(b, b + 1))
        assert torch.allclose(f_one[0], f_all[b], rtol=1e-9, atol=1e-12)
        for one, full in zip(g_one, g_all):
            assert torch.allclose(one[0], full[b], rtol=1e-7, atol=1e-9)


@pytest.mark.slow
def test_stress_benchmark_element_whose_gradient_was_not_finite_in_its_batch():
    """Element 305 of the stress benchmark's (K = 19, d = 1, float32) batch (seed 0): six flat directions; its
    gradient with respect to the lower bounds was NaN / 1e31 in the batch of 1000 (the line steps ran as long as any
    element improved), finite alone."""
    gen = torch.Generator().manual_seed(0)
    for K, d in TASK_SIZES:  # (the benchmark's sequence of instances up to that batch)
        for dtype in (torch.float32, torch.float64):
            A, q, mu, lower, _, _ = near_psd_instance(gen, 1000, K, d)
            if (K, d, dtype) == (19, 1, torch.float32):
                ins = [t.clone().requires_grad_() for t in (A, q, mu, lower)]
                solve_cone_qp(*ins).sum().backward()
                assert all(torch.isfinite(t.grad).all() for t in ins)
                alone = [t[305:306].clone().requires_grad_() for t in (A, q, mu, lower)]
                solve_cone_qp(*alone).sum().backward()
                for one, full in zip(alone, ins):
                    assert torch.allclose(one.grad[0], full.grad[305], rtol=1e-4, atol=1e-5)
                return


def test_gradcheck_of_the_flat_projection_alone():
    """(A, q) → (Ã, q̃, Π_N) through A = F Fᵀ + E (E: fixed eigenvalues ±2e-8 on the null space) and q = F w + 1e-9:
    the first-order eigenvector perturbation of the backward pass against finite differences."""
    from diffcontact.solver.least_norm import FlatProjection

    gen = torch.Generator().manual_seed(0)
    B, n, r = 3, 4, 2
    F = torch.randn(B, n, r, generator=gen, dtype=torch.float64)
    w = torch.randn(B, r, generator=gen, dtype=torch.float64)
    _, V = torch.linalg.eigh(F @ F.mT)
    E = 3e-8 * V[..., :1] @ V[..., :1].mT - 2e-8 * V[..., 1:2] @ V[..., 1:2].mT
    used = torch.ones(B, n, dtype=torch.bool)

    def fn(F, w):
        A = F @ F.mT + E
        out = FlatProjection.apply(0.5 * (A + A.mT), (F @ w[..., None])[..., 0] + 1e-9, used, 1e-6, torch.arange(B))
        return out[:3]

    inputs = (F.clone().requires_grad_(), w.clone().requires_grad_())
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize(
    "seed,K,b,status",
    [
        (301, 4, 171, Status.CONVERGED),
        (309, 4, 32, Status.CONVERGED),
        (310, 4, 34, Status.CONVERGED),
        (2, 19, 95, Status.CONVERGED),
        (2, 19, 99, Status.INACCURATE),
    ],
)
def test_stalled_least_norm_stage_ends_at_the_minimum_norm_minimiser(seed, K, b, status):
    """Elements of degenerate batches (tests/test_solver_robustness.py; d = 2; K = 4 with two flat directions, K = 19
    with 16 and 12) where the least-norm stage's augmented Lagrangian stalled at its inner solves' accuracy: the
    answer is a minimiser with the norm of the two-stage Clarabel reference.  It used to be the stage's start (6–23×
    larger in norm, status 0); then the last iterate where its miss was below 1e-7 (seed 301: a
    minimiser only to 1e-6 by the natural residual, INACCURATE), else still the start (the K = 19 cases: norm 0.658
    and 1.78 against 0.584 and 1.416, status 0 and INACCURATE).  Now the stalled iterate is finished by a proximal
    step, a minimiser to rounding; INACCURATE where its miss stayed above ALM_FLOOR (2e-7: its norm is least only
    to that)."""
    from test_solver_robustness import _degenerate_batch

    A, q, mu, lower, active = _degenerate_batch(torch.Generator().manual_seed(seed), 200, K, 2)
    one = slice(b, b + 1)
    f, info = solve_cone_qp(A[one], q[one], mu[one], lower[one], active[one], return_info=True)
    assert info.status.tolist() == [status]
    used, rows = active[b], active[b].repeat_interleave(2)  # (the reference on the active contacts)
    assert (f[0, ~rows] == 0).all()
    Ab, qb = _projected(A[b][rows][:, rows].numpy(), q[b][rows].numpy())
    mub, lb, fb = mu[b][used].numpy(), lower[b][used].numpy(), f[0][rows].numpy()
    f_ref, obj_ref = clarabel_solve(Ab, qb, mub, lb, 2)
    f_min = clarabel_min_norm(Ab, qb, mub, lb, 2, f_ref)
    scale = max(1.0, np.abs(f_ref).max())
    obj_scale = max(1.0, abs(obj_ref), np.abs(qb).max() * scale)
    assert abs(0.5 * fb @ Ab @ fb + qb @ fb - obj_ref) <= 1e-7 * obj_scale
    one_row = np.zeros(1, dtype=np.int64)
    natural = natural_residual(
        Ab[None], qb[None], mub[None], lb[None], np.ones((1, len(mub)), bool), fb[None], 2, one_row
    )
    assert natural[0] <= 1e-7  # a usable minimiser (acceptable_tol; the stalled iterates alone: 6e-7 – 8e-7)
    # not larger than the reference's least norm (seed 2, element 99: smaller by 8e-6, Clarabel's accuracy there)
    assert np.linalg.norm(fb) - np.linalg.norm(f_min) <= 1e-6 * scale
    assert np.linalg.norm(f_min) - np.linalg.norm(fb) <= 1e-5 * scale


def test_a_pass_keeps_the_previous_answer_where_that_is_nearer():
    """A near-PSD gyroscope problem of `diffcontact bench near-psd` (float32 data, solved in float64; a flat
    direction): pass 1 (the interior point to 1e-5, then polishing) ends at a residual of 3.9e-12, short of rounding
    level, so pass 2 runs, and ends at 9.5e-10 (the interior point to 1e-10, which polishing cannot improve there).
    Pass 1's answer is kept: CONVERGED (it used to be pass 2's, INACCURATE), and the minimum-norm minimiser."""
    A = torch.tensor(
        [
            [0.5826688408851624, 0.1416793018579483, -0.7539125680923462],
            [0.1416793018579483, 1.3291927576065063, -0.4605324864387512],
            [-0.7539125680923462, -0.4605324864387512, 1.0348381996154785],
        ],
        dtype=torch.float64,
    )[None]
    q = torch.tensor([[0.15119832754135132, -0.16317808628082275, -0.15282560884952545]], dtype=torch.float64)
    mu, lower = torch.tensor([[0.8282952308654785]], dtype=torch.float64), torch.tensor([[0.007671198807656765]])
    f, info = solve_cone_qp(A, q, mu, lower.double(), return_info=True)
    assert info.status.tolist() == [Status.CONVERGED] and info.residual[0] <= 1e-10
    Ab, qb = _projected(A[0].numpy(), q[0].numpy())
    mub, lb, fb = mu[0].numpy(), lower[0].double().numpy(), f[0].numpy()
    f_ref, obj_ref = clarabel_solve(Ab, qb, mub, lb, 3)
    f_min = clarabel_min_norm(Ab, qb, mub, lb, 3, f_ref)
    scale = max(1.0, np.abs(f_ref).max())
    obj_scale = max(1.0, abs(obj_ref), np.abs(qb).max() * scale)
    assert abs(0.5 * fb @ Ab @ fb + qb @ fb - obj_ref) <= TOL_OBJ * obj_scale
    assert np.abs(fb - f_min).max() <= 1e-6 * scale


@pytest.mark.parametrize("K,d,seed,element", [(3, 2, 1, 98), (3, 2, 291, 126), (8, 1, 2, 128)])
def test_the_answer_with_gradients_is_the_answer_without(K, d, seed, element):
    """Degenerate fuzz elements (two flat directions; a contact with a zero row, pushed apart by q) whose first
    minimiser lies far out and is brought back by the Tikhonov solve (problem._near_least_norm) exactly to the
    least-norm end of the set.  The gradient path then took the set for a single point (flat.nonunique compares
    with the least-norm point) and returned another, arbitrary minimiser of its uncentred solve: f_n = 0.27 where
    the answer is 0, CONVERGED (KKT residual 0.27).  The two minimisers now mark the set as not a point, centred on
    their midpoint.  (Exposed when polishing reached the Tikhonov minimiser exactly; before, it stopped short.)"""
    from test_solver_robustness import _degenerate_batch

    A, q, mu, lower, active = _degenerate_batch(torch.Generator().manual_seed(seed), 200, K, d)
    A, q, mu, lower, active = (t[element : element + 1] for t in (A, q, mu, lower, active))
    plain = solve_cone_qp(A, q, mu, lower, active)
    ins = [t.clone().requires_grad_() for t in (A, q, mu, lower)]
    f, info = solve_cone_qp(*ins, active=active, return_info=True)
    f = f.detach()
    assert info.status[0] == Status.CONVERGED
    assert (f - plain).abs().max() <= 1e-9 * plain.abs().max().clamp_min(1.0)
    rows = active[0].repeat_interleave(d).numpy()
    sub = A[0].numpy()[np.ix_(rows, rows)], q[0].numpy()[rows], mu[0].numpy()[active[0]], lower[0].numpy()[active[0]]
    assert kkt_residual(*sub, f[0].numpy()[rows], d) <= 1e-9


@pytest.mark.parametrize("element", [159, 172, 182])
def test_a_far_stall_that_is_a_minimiser_already_is_not_moved_by_the_proximal_step(element):
    """Degenerate fuzz elements (K = 19, d = 2, seed 1; 5–9 flat directions) whose least-norm stage stalls at a miss
    of about 1e-10, already at the least-norm point, far from its start.  The proximal step (curvature 1e-10 along
    the flat directions: ill-conditioned) moved such a point by up to 0.23 (norm 49.5627 against the least 49.5605,
    KKT residual 6.7e-3) once polishing made the stage's inner solves exact; before, the stage stalled elsewhere,
    0.8e-3 – 1.8e-3 from the least-norm point with a KKT residual of 2e-5 – 9e-5.  Where the step raises the norm, a
    far stall that is a minimiser to ALM_ACCEPT is now kept as it is (where it lowers it, as for element 157 of
    K = 19, d = 1, the step corrects the range part inherited from a start far out, and is taken)."""
    from test_solver_robustness import _degenerate_batch

    K, d = 19, 2
    A, q, mu, lower, active = _degenerate_batch(torch.Generator().manual_seed(1), 200, K, d)
    A, q, mu, lower, active = (t[element : element + 1] for t in (A, q, mu, lower, active))
    f, info = solve_cone_qp(A, q, mu, lower, active, return_info=True)
    assert info.status[0] == Status.CONVERGED
    rows = active[0].repeat_interleave(d).numpy()
    sub = A[0].numpy()[np.ix_(rows, rows)], q[0].numpy()[rows], mu[0].numpy()[active[0]], lower[0].numpy()[active[0]]
    f_ref, _ = clarabel_solve(*sub, d)
    f_min = clarabel_min_norm(*sub, d, f_ref)
    x = f[0].numpy()[rows]
    assert kkt_residual(*sub, x, d) <= 1e-6
    assert np.linalg.norm(x) <= np.linalg.norm(f_min) * (1 + 1e-9)
    assert np.abs(x - f_min).max() <= 1e-4 * np.abs(f_min).max()


def test_a_badly_row_scaled_effective_mass_is_not_taken_for_a_singular_one():
    # 12 limits of a rope trained on noisy data (float32, from training): links compressed far past the stretch
    # limit make bend rows of A 1e5 times the stretch rows (diagonal 3.9e5 against 1.1-2.3).  Its eigenvalues 0.34 …
    # 2.9 are real (float32 rounds A's entries relative to its rows: the product Z Zᵀ); judged against τ·max(diag A)
    # = 4.7 they counted as 7 flat directions, and the least-norm stage ended NUMERICAL (1329 such failures in one
    # noisy Rope training).  Judged against the scale of their own rows, they are not flat: a regular problem.
    from pathlib import Path

    data = np.load(Path(__file__).parent / "data" / "noisy_rope_limits.npz")
    A, q = torch.from_numpy(data["A"])[None], torch.from_numpy(data["q"])[None]
    mu = torch.zeros(1, A.shape[-1])
    f, info = solve_cone_qp(A, q, mu, on_failure="count", return_info=True)
    assert info.status.tolist() == [Status.CONVERGED]
    zeros = np.zeros(A.shape[-1])
    ref, _ = clarabel_solve(A[0].double().numpy(), q[0].double().numpy(), zeros, zeros, 1)
    assert np.abs(f[0].double().numpy() - ref).max() <= 1e-4 * max(1.0, np.abs(ref).max())


def _noisy_rope_problem():
    """The second of two limit problems of a rope evaluated after training on noisy data (float64): its effective
    mass's diagonal spans 1.3 … 4.5e9 (links compressed to almost nothing; condition about 1e11, 11 of its 16
    directions flat).  Returns A, q, mu, active, each (2, …): the pair as the evaluation batched it."""
    from pathlib import Path

    data = np.load(Path(__file__).parent / "data" / "noisy_rope_batch.npz")
    return tuple(torch.from_numpy(data[k]) for k in ("A", "q", "mu", "active"))


def test_an_ill_conditioned_rope_problem_converges_wherever_it_sits_in_the_batch():
    """The tight pass (the interior point to 1e-10) on this problem lost positive definiteness of its Newton matrix
    near the end, beyond the one diagonal shift the kernel tried, and ended NUMERICAL, which also discarded pass 1's
    usable answer; through MKL's alignment-dependent arithmetic that happened second in the pair and not alone.  The
    kernel now raises the shift up to 1e-7 of the diagonal, and a failed pass keeps the previous pass's answer: the
    problem converges wherever it sits, to answers that agree to the accuracy its conditioning allows, and to the
    objective of Clarabel's solution of the problem as the solver states it (the flat directions removed)."""
    A, q, mu, active = _noisy_rope_problem()
    answers = []
    for order in ([1], [0, 1], [1, 0], [1, 1]):
        f, info = solve_cone_qp(A[order], q[order], mu[order], None, active[order], return_info=True)
        at = order.index(1)
        assert info.status[at] == Status.CONVERGED, order
        answers.append(f[at].numpy())
    scale = max(1.0, np.abs(answers[0]).max())
    assert max(np.abs(a - answers[0]).max() for a in answers) <= 1e-6 * scale  # (measured: 1.5e-8)
    used = active[1].numpy()
    Ab, qb = _projected(A[1].numpy()[np.ix_(used, used)], q[1].numpy()[used])
    mub, lb, fb = mu[1].numpy()[used], np.zeros(int(used.sum())), answers[0][used]
    f_ref, obj_ref = clarabel_solve(Ab, qb, mub, lb, 1)
    obj_scale = max(1.0, abs(obj_ref), np.abs(qb).max() * max(scale, np.abs(f_ref).max()))
    assert abs(0.5 * fb @ Ab @ fb + qb @ fb - obj_ref) <= 1e-7 * obj_scale  # (measured: 2.9e-8)
    # a minimiser no longer than Clarabel's least-norm one (ours 5.8, Clarabel's 13.9: its accuracy at 1e11)
    assert np.linalg.norm(fb) <= np.linalg.norm(clarabel_min_norm(Ab, qb, mub, lb, 1, f_ref)) + 1e-6 * scale


def test_a_pass_that_fails_numerically_keeps_the_previous_passs_answer(monkeypatch):
    """Where the tight pass ends NUMERICAL (a Newton matrix that no shift makes positive definite), the element
    keeps pass 1's answer (usable: residual ≤ acceptable_tol), instead of failing with zero impulses."""
    from diffcontact.solver import kernel, problem

    A, q, mu, active = (t[1:] for t in _noisy_rope_problem())
    expected = solve_cone_qp(A, q, mu, None, active)
    solve = kernel.solve
    tight = []

    def failing_tight_pass(*args, **kwargs):
        out = solve(*args, **kwargs)
        if kwargs["ipm_tol"] < problem.IPM_TOL:  # (pass 2: the method run to the final tolerance)
            idx = args[7]
            out.status[idx] = Status.NUMERICAL
            tight.append(len(idx))
        return out

    monkeypatch.setattr(kernel, "solve", failing_tight_pass)
    f, info = solve_cone_qp(A, q, mu, None, active, return_info=True)
    assert tight, "pass 2 never ran: the test no longer exercises the policy"
    assert info.status[0] <= Status.INACCURATE and info.residual[0] <= 1e-7
    # a minimiser as good as the tight one (another point of the nearly flat set: they differ by 6e-4 relative)
    used = active[0].numpy()
    Ab, qb = _projected(A[0].numpy()[np.ix_(used, used)], q[0].numpy()[used])
    fb, eb = f[0].numpy()[used], expected[0].numpy()[used]
    obj_scale = max(1.0, np.abs(qb).max() * np.abs(eb).max())
    assert abs((0.5 * fb @ Ab @ fb + qb @ fb) - (0.5 * eb @ Ab @ eb + qb @ eb)) <= 1e-7 * obj_scale


def test_a_flat_problem_whose_first_solve_fails_is_solved_with_curvature_on_its_flat_directions():
    """A training batch of a Rope on data with noise 0.05 (float32, 50 limit problems, saved by the run in
    solver_failures.npz): element 49's effective mass spans 1.1 … 1.2e9 on its diagonal, with flat directions.  Its
    first solve stalls at a residual of 1.9e-7 (MAX_ITER) and its tight pass ends NUMERICAL, so it failed, with
    gradients and without (alone it converges: its projection is computed with the batch's).  The solve with
    curvature on the flat directions (``problem._near_least_norm``), until then only for minimisers far out,
    converges; it now replaces a failed first solve, and with gradients the problem is centred on its answer."""
    from pathlib import Path

    data = np.load(Path(__file__).parent / "data" / "noisy_rope_training_batch.npz")
    A, q, mu, active = (torch.from_numpy(data[k]) for k in ("A", "q", "mu", "active"))
    plain, info = solve_cone_qp(A, q, mu, None, active, return_info=True)
    assert (info.status == Status.CONVERGED).all() and info.residual[49] <= 1e-10
    ins = [t.clone().requires_grad_() for t in (A, q, mu)]
    f, info_g = solve_cone_qp(*ins, None, active, return_info=True)
    assert (info_g.status == Status.CONVERGED).all()
    f.pow(2).sum().backward()
    assert all(bool(torch.isfinite(t.grad).all()) for t in ins)
    scale = float(plain[49].abs().max().clamp_min(1.0))
    assert float((f[49].detach() - plain[49]).abs().max()) <= 1e-5 * scale


def test_a_sliding_face_at_a_tiny_lower_bound_is_solved_with_more_curvature():
    """The restitution problem of a cube sliding flat on the table (4 corners, A of rank 6: six flat directions),
    rolled out by a model that learned e = 3e-7: its lower bounds 4e-8 cut the cones' apexes.  The first solve
    stalls at a residual of 2.6e-6 (MAX_ITER), and so does the solve with curvature 1e-12 on the flat directions;
    it failed a whole evaluation of the real cube tosses.  With the curvature raised to 1e-9 it converges: the
    velocity change and objective of the reference layer (whose natural residual here is 6e-9; the two-stage
    Clarabel reference's is 4e-6, its velocities 2e-7 off), the least norm of the two-stage reference, inside the
    cones and above the bounds, with finite gradients."""
    from pathlib import Path

    from diffcontact.solver.reference import solve_cone_qp_reference

    data = np.load(Path(__file__).parent / "data" / "sliding_face_lower_bound.npz")
    A, q, mu, lower, active = (torch.from_numpy(data[k])[None] for k in ("A", "q", "mu", "lower", "active"))
    f, info = solve_cone_qp(A, q, mu, lower, active, return_info=True)
    assert info.status.tolist() == [Status.CONVERGED]
    fb, lb, mub, Ab, qb = f[0].numpy(), lower[0].numpy(), mu[0].numpy(), A[0].numpy(), q[0].numpy()
    r = solve_cone_qp_reference(A, q, mu, lower, active)[0].numpy()
    assert np.abs(Ab @ (fb - r)).max() <= 1e-6 * np.abs(qb).max()  # the same velocity change (measured 2.6e-9)
    objective = lambda x: 0.5 * x @ Ab @ x + qb @ x  # noqa: E731
    assert abs(objective(fb) - objective(r)) <= 1e-5 * abs(objective(r))  # (measured 5e-7)
    fk = fb.reshape(4, 3)
    assert (fk[:, 0] >= lb - 1e-12).all() and (mub * fk[:, 0] - np.linalg.norm(fk[:, 1:], axis=1) >= -1e-9).all()
    Ap, qp = _projected(Ab, qb)
    f_min = clarabel_min_norm(Ap, qp, mub, lb, 3, clarabel_solve(Ap, qp, mub, lb, 3)[0])
    assert np.linalg.norm(fb) <= np.linalg.norm(f_min) * (1 + 1e-5)  # (the reference layer's: 1.29 times)
    ins = [t.clone().requires_grad_() for t in (A, q, mu, lower)]
    f_g, info_g = solve_cone_qp(*ins, active, return_info=True)
    assert info_g.status.tolist() == [Status.CONVERGED]
    f_g.pow(2).sum().backward()
    assert all(bool(torch.isfinite(t.grad).all()) for t in ins)


def test_flat_tol_sets_which_small_eigenvalue_is_rounding():
    """A (2 × 2) with eigenvalues 1 and 1e-8 and the minimiser f* = (1, 2) inside the cones (q = −A f*): by default
    (1e-6 for a float64 input) the small eigenvalue is rounding, q's tiny part along it is dropped and the answer is
    the least-norm minimiser of the rest, f*'s part along the large eigenvector; with ``flat_tol`` 1e-10 it is an
    eigenvalue like any other, and the answer is f*."""
    c = 2**-0.5
    R = torch.tensor([[c, -c], [c, c]], dtype=torch.float64)
    A = (R @ torch.diag(torch.tensor([1.0, 1e-8], dtype=torch.float64)) @ R.T)[None]
    f_star = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    q = -(A @ f_star[..., None])[..., 0]
    mu = torch.zeros(1, 2, dtype=torch.float64)
    flat = solve_cone_qp(A, q, mu)
    assert torch.allclose(flat, (f_star @ R[:, :1]) * R[:, 0], atol=1e-9)  # (1.5, 1.5)
    assert torch.allclose(solve_cone_qp(A, q, mu, flat_tol=1e-10), f_star, atol=1e-6)
    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="flat_tol"):
            solve_cone_qp(A, q, mu, flat_tol=bad)
