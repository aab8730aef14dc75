"""Reference back end of the contact solver: cvxpylayers (diffcp + SCS) at a tight tolerance.

It has the signature of :func:`diffcontact.solver.solve_cone_qp` and is the oracle of the tests and the
baseline of the solver benchmark. It needs the optional extra ``diffcontact[reference]``; it is slow
(milliseconds per problem), solves in float64 numpy whatever the input dtype, and returns the input dtype.
"""

from __future__ import annotations

import functools

import torch

from diffcontact.solver.problem import check_problem


def _require_reference():
    try:
        import cvxpy as cp
        from cvxpylayers.torch.cvxpylayer import CvxpyLayer
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the reference contact solver needs the optional extra: pip install 'diffcontact[reference]'"
        ) from err
    return cp, CvxpyLayer


@functools.lru_cache(maxsize=64)
def _layer(n_contacts: int, dim: int, solver: str | None):
    """A CvxpyLayer for K contacts of dimension d, built once per (K, d) and reused."""
    cp, CvxpyLayer = _require_reference()
    n = n_contacts * dim
    factor = cp.Parameter((n, n))  # A = factorᵀ factor
    q = cp.Parameter(n)
    mu = cp.Parameter(n_contacts, nonneg=True)
    lower = cp.Parameter(n_contacts, nonneg=True)
    off = cp.Parameter(n_contacts, nonneg=True)  # 1 for inactive contacts
    f = cp.Variable(n)
    normal = f[0::dim]
    cons = [normal >= lower, cp.multiply(off, normal) == 0]
    if dim > 1:
        for i in range(n_contacts):
            cons.append(cp.norm(f[i * dim + 1 : (i + 1) * dim]) <= mu[i] * normal[i])
    objective = cp.Minimize(0.5 * cp.sum_squares(factor @ f) + q @ f)
    problem = cp.Problem(objective, cons)
    assert problem.is_dpp()
    params = [factor, q, mu, lower, off] if dim > 1 else [factor, q, lower, off]
    return CvxpyLayer(problem, parameters=params, variables=[f], solver=solver)


def psd_factor(A: torch.Tensor) -> torch.Tensor:
    """F with FᵀF = A for symmetric PSD A: (B, n, n), by a symmetric square root (singular A allowed)."""
    evals, evecs = torch.linalg.eigh(A)
    return (evecs * evals.clamp_min(0.0).sqrt().unsqueeze(-2)) @ evecs.mT


def solve_cone_qp_reference(
    A: torch.Tensor,
    q: torch.Tensor,
    mu: torch.Tensor,
    lower: torch.Tensor | None = None,
    active: torch.Tensor | None = None,
    *,
    eps: float = 1e-10,
    max_iters: int = 100_000,
) -> torch.Tensor:
    """Solve the batch of contact cone QPs with cvxpylayers/SCS (see :func:`~diffcontact.solver.solve_cone_qp`).

    A: (B, K·d, K·d) PSD; q: (B, K·d); mu, lower: (B, K); active: (B, K) bool.  Returns f: (B, K·d).
    Differentiable with respect to A (through a symmetric square root), q, mu and lower.
    """
    A, q, mu, lower, active, dim = check_problem(A, q, mu, lower, active)
    dtype = A.dtype
    K = mu.shape[-1]
    layer = _layer(K, dim, None)
    off = (~active).to(torch.float64)
    args = [psd_factor(A.double()), q.double(), mu.double() * active, lower.double() * active, off]
    if dim == 1:
        del args[2]
    (f,) = layer(*args, solver_args={"solve_method": "SCS", "eps_abs": eps, "eps_rel": eps, "max_iters": max_iters})
    f = f * active.repeat_interleave(dim, dim=-1)
    return f.to(dtype)
