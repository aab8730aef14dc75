"""Every threshold of the contact solver's policy, with its reason, in one record: :data:`POLICY`.

The modules that use a threshold bind it to a module-level name (``IPM_TOL = POLICY.ipm_tol``): numba's compiled
functions read module globals as constants, and a test can still replace one.  docs/solver.md ("The policy's
thresholds") lists the same fields and values; ``tests/test_solver_policy.py`` keeps the two the same.
"""

from __future__ import annotations

from dataclasses import dataclass, fields


@dataclass(frozen=True)
class SolverPolicy:
    """The solver's thresholds (all relative unless a unit is named)."""

    # what a caller may change (``solve_cone_qp``, ``ContactSolver``): these are their defaults
    tol: float = 1e-10  # the target of the scaled KKT residual
    acceptable_tol: float = 1e-7  # a residual still usable at the iteration limit (INACCURATE); above it, a failure
    max_iter: int = 60  # interior-point iterations a pass
    # the interior-point method and its polishing
    ipm_tol: float = 1e-5  # the method's target before polishing: measured fastest in 1e-8 … 1e-3
    rounding_tol: float = 1e-13  # polishing reached rounding level: converged without a pass of the method to tol
    polish_steps: int = 3  # factorisations per polishing pass
    polish_retry_steps: int = 12  # ... in the last attempt, on elements still unsolved: at a contact whose lower bound
    # cuts its cone's apex (a learned e near 0: a bound 1e-4 of the answer), Newton converges slowly at first (5 needed)
    start_margin: float = 0.1  # how far inside the cones the first start lies: measured over 0.001 … 3, K 1 … 19
    robust_margin: float = 1.0  # CVXOPT's start, that of the retries: slower on average, more robust
    weak_tol: float = 1e-6  # a multiplier ≤ this × max(1, ‖slack‖) is weakly active (a stick/slip or touch switch)
    # large friction coefficients
    mu_checked: float = 10.0  # above it an answer is also checked by its natural residual (the scaled test is exact
    # below: worst natural residual of a usable answer 6e-11 at μ ≤ 10 over 10,800 random problems)
    mu_free: float = 1e4  # from it a contact is solved free first, and again scaled for sliding where it leaves the
    # cone (at 1e6, gradients at μ 1e4 … 1e6 were wrong by 3e-5; 2e-9 at 1e4)
    mu_cap: float = 1e4  # the last attempt: failed elements with a larger μ solved with μ capped at this (measured
    # 1e3 … 1e5; the same value as mu_free by measurement, not by definition)
    mu_max: float = 1e100  # the largest μ accepted: far beyond sticking, far below the ~1e160 where scaling overflows
    # problems whose minimisers are not unique (flat directions)
    row_floor: float = 1e-2  # an eigenvector's row scale (Σ|v_i|√A_ii)² is trusted down to this × max(diag A) (on
    # rows 1e5 times apart a real eigenvalue is 9e-7 × it; the stress cases' rounding, absolute, 1e-9 × it)
    far: float = 1e3  # a minimiser farther than this × its range part is solved again for the least-norm one
    tikhonov: float = 1e-12  # ... with this curvature (relative) on its flat directions
    tikhonov_max: float = 1e-9  # ... raised 1000 times where that solve fails too, up to this (a sliding face at a
    # lower bound 4e-8 that cuts its cones' apexes failed at 1e-12 and converged at 1e-9)
    q_tol: float = 0.1  # up to this, drift of the constraint velocities is dropped where a flat direction enters a cone
    unique_tol: float = 1e-6  # a set of minimisers narrower than this is a point (rounding alone opens ~1e-8)
    alm_rho: float = 1e4  # the augmented Lagrangian stage (several flat directions): penalty, relative to the Hessian
    alm_rho_max: float = 1e5  # ... and its largest
    alm_steps: int = 20  # ... steps
    alm_tol: float = 1e-13  # ... relative miss of the equality at convergence
    alm_accept: float = 1e-9  # ... below which an iterate counts as a minimiser
    alm_floor: float = 1e-7  # a stalled iterate steps on until its miss is below this (the inner solves' accuracy)
    alm_far: float = 1e4  # ... when it stalls this many times farther from its start than its miss (not at a point)
    wide_flat_tol: float = 1e-10  # the contact model's A of a system without joints is flat below this: its
    # rounding is ≲ n·eps·max(diag A) (2e-13 at Rope200's 399 rows), and a rope compressed past every limit has a
    # real eigenvalue 1.3e-8 × max(diag A), which 1e-6 took for rounding (impulses 82 off, reported converged)
    v_rounding: float = 1e-9  # parts of a unit flat direction up to this are the eigensolver's rounding
    prox: float = 1e-10  # the proximal step that finishes a stalled least-norm stage: curvature relative to ref

    def table(self) -> list[tuple[str, float]]:
        """(field, value) of every threshold, in order."""
        return [(f.name, getattr(self, f.name)) for f in fields(self)]


POLICY = SolverPolicy()
