"""Implicit differentiation of the standard-form cone QP at its solution (one autograd Function).

The optimality conditions P z + c + Gᵀλ = 0, G z + s = h, s ∘ λ = 0 (Jordan product per cone) are
linearised at the returned iterate, with ds = dh − G dz eliminated:

    [  P        Gᵀ  ] [dz]   [ −dP·z − dc ]
    [ −L(λ)G   L(s) ] [dλ] = [  −L(λ) dh  ]

where L(x) is the arrow matrix of x (x ∘ y = L(x) y).  At a strictly complementary solution this matrix is
nonsingular although L(s) and L(λ) are singular on the cone boundary, so it gives the exact derivative of the
solution map (a sliding contact's direction turning with the data included).  For an incoming gradient
ḡ = ∂L/∂z the adjoint system Kᵀ[u; v] = [ḡ; 0] gives

    ∂L/∂c = −u,   ∂L/∂P = −½(u zᵀ + z uᵀ),   ∂L/∂h = −L(λ) v   (h = −l on the rays: ∂L/∂l = λ_l·v_l).

The chain rule through the substitution f = γ·T⊙z (P = T A T, c = T q/γ, T = S·D(μ)) is applied in closed
form: ∂L/∂A = −½(T u (T z)ᵀ + T z (T u)ᵀ) and matrix–vector products for ∂L/∂T.  No backpropagation through the
iterations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from diffcontact.solver import kernel, kkt, scaling
from diffcontact.solver.kernel import IPMResult
from diffcontact.solver.kkt import contact_dims
from diffcontact.solver.status import is_failure


@dataclass
class ScaledSolution:
    """A solved batch and its substitution f = γ·T⊙z, T = S·D (see ``problem.py``); everything the backward
    pass needs, float64 numpy (C-contiguous), no autograd.  Shapes: B batch, K contacts, n = K·d."""

    A: np.ndarray  # (B, n, n) the symmetrised A
    q: np.ndarray  # (B, n)
    T: np.ndarray  # (B, n) S·D on active rows, 0 elsewhere
    S: np.ndarray  # (B, n) S on active rows (∂T/∂μ on the tangential rows)
    gamma: np.ndarray  # (B,)
    lower_scale: np.ndarray  # (B, K) ∂l̂/∂lower: 1/(σγ) on active contacts with a non-negligible bound, else 0
    slide: np.ndarray  # (B, K) −∂c_n/∂μ of frictionless sliding contacts (σ‖g_t‖/γ), else 0
    z: np.ndarray  # (B, n) solution in z
    result: IPMResult


class ImplicitConeQP(torch.autograd.Function):
    """f(A, q, mu, lower) of a batch solved beforehand (``ScaledSolution``), differentiated implicitly.

    The backward pass solves the adjoint system once per element and applies the chain rule of the scaling
    in closed form (matrix–vector products, no (B, n, n) intermediate besides ∂L/∂A itself).  Tensors on the CPU.
    """

    @staticmethod
    def forward(ctx, A, q, mu, lower, sol: ScaledSolution):  # noqa: D102
        # (the form with ctx: the one with setup_context binds the arguments by signature on every call, ≈ 20 µs)
        ctx.sol = sol
        ctx.dtypes = (A.dtype, q.dtype, mu.dtype, None if lower is None else lower.dtype)
        return _as_dtype(torch.from_numpy(scaling.unscale(sol.gamma, sol.T, sol.z)), A.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable  # (which torch types as making ctx positional-only)
    def backward(ctx, grad_f):  # noqa: D102  # pyright: ignore[reportIncompatibleMethodOverride]
        sol: ScaledSolution = ctx.sol
        res = sol.result
        d = res.d
        gf = np.ascontiguousarray(_as_dtype(grad_f, torch.float64).numpy())
        failed = is_failure(res.status)  # (counted failures: their impulses were set to 0, a constant)
        if np.count_nonzero(failed):
            gf = gf.copy()
            gf[failed] = 0.0  # (so their gradients are 0, and their unsolved state never enters the adjoint)
        u, v_l = adjoint_solve(res, scaling.unscale(sol.gamma, sol.T, gf), skip=failed)
        need = np.array(ctx.needs_input_grad[:4], dtype=np.bool_)
        arrays = (u, v_l, sol.z, gf, sol.A, sol.q, sol.T, sol.S, sol.gamma, res.lam_l, res.on_l, sol.lower_scale)
        grads = scaling.chain_rule_batch(*arrays, sol.slide, contact_dims(d), need)
        return (*(_as_dtype(torch.from_numpy(g), dt) if want else None for g, want, dt in zip(grads, need, ctx.dtypes)),
                None)  # fmt: skip


def _as_dtype(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """t in this dtype (``t.to(dtype)`` costs a µs even where it changes nothing: three times in a small call)."""
    return t if t.dtype == dtype else t.to(dtype)


def adjoint_solve(res: IPMResult, g: np.ndarray, skip: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Solve Kᵀ[u; v] = [g; 0] (module docstring); returns u: (B, n) and the rays' v: (B, K).

    Solved in the compiled kernel (``kernel.adjoint``); where K is singular (a degenerate solution: a contact exactly
    at a stick/slip or touch/separate switch) the dense system is solved by least squares instead.  ``skip`` (B,)
    bool: elements whose solve failed (g is 0 there): u = v = 0, without a least-squares solve of their K, which
    holds the interior-point method's unfinished state (a LAPACK SVD that does not converge on it).
    """
    u, v_l, ok = kernel.adjoint(res, g)
    if skip is not None and np.count_nonzero(skip):
        u[skip], v_l[skip] = 0.0, 0.0
        ok = ok | skip
    if np.count_nonzero(ok) < len(ok):
        u[~ok], v_l[~ok] = _adjoint_lstsq(res, g, ~ok)
    return u, v_l


def _adjoint_lstsq(res: IPMResult, g: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares adjoint for the selected (degenerate) elements, weakly active cones taken as inactive."""
    d = res.d
    n, K = g.shape[-1], res.on.shape[-1]
    P = kernel.scaled_matrix(np.ascontiguousarray(res.A[sel]), np.ascontiguousarray(res.T[sel]))
    s_l, lam_l, s_q, lam_q, on, on_l = (
        np.ascontiguousarray(t[sel]) for t in (res.s_l, res.lam_l, res.s_q, res.lam_q, res.on, res.on_l)
    )
    Kmat = kkt.kkt_matrix_batch(P, s_l, lam_l, s_q, lam_q, on, on_l, contact_dims(d), True)
    rhs = np.zeros(Kmat.shape[:2])
    rhs[:, :n] = g[sel]
    # The least-squares solution of least norm, by the pseudo-inverse with LAPACK's default cut-off of singular
    # values (that of numpy.linalg.lstsq).  (torch.linalg.lstsq gave results that varied from run to run in the
    # last digits, amplified by the conditioning of the degenerate K.)
    sol = np.matmul(pseudo_inverse(np.swapaxes(Kmat, -1, -2)), rhs[..., None])[..., 0]
    return sol[:, :n], sol[:, n : n + K]


def pseudo_inverse(M: np.ndarray) -> np.ndarray:
    """The pseudo-inverse of each (m, m) matrix of M (B, m, m), with LAPACK's default cut-off of singular values.

    LAPACK's divide-and-conquer SVD (gesdd, numpy's) fails to converge on some degenerate KKT matrices, finite and
    of norm 1 (one from a noisy Rope training is ``tests/data/degenerate_kkt.npy``).  Then the pseudo-inverse comes
    from the symmetric eigendecomposition of MᵀM instead: M⁺ = (MᵀM)⁺ Mᵀ, keeping the singular values above
    √(m·ε) of the largest (squaring halves the digits the cut-off can resolve)."""
    eps = M.shape[-1] * np.finfo(np.float64).eps
    try:
        return np.linalg.pinv(M, rcond=eps)
    except np.linalg.LinAlgError:
        G = np.swapaxes(M, -1, -2) @ M
        w, V = np.linalg.eigh(G)  # (B, m), (B, m, m), ascending
        inv = np.where(w > eps * w[..., -1:], 1.0 / np.where(w > 0, w, 1.0), 0.0)
        return (V * inv[..., None, :]) @ np.swapaxes(V, -1, -2) @ np.swapaxes(M, -1, -2)
