"""The contact model (paper Sec. 3, Eqs. 5–17): compression, then restitution, then the velocity jump.

    compression   f_c = argmin ½fᵀAf + fᵀ(J_C v⁻)                     s.t. f in the friction cones
    restitution   f_r = argmin ½fᵀAf + fᵀ(J_C v_c − v*_C)             s.t. cones, f_n >= e f_c,n
    apply         v⁺ = v⁻ + M̂⁻¹J_Cᵀ(f_c + f_r)

CM uses A; CMr uses A + r I (r = 0.01) inside both problems while velocities still use M̂⁻¹. The target
v*_C (paper Suppl. F) is a fraction of depth/dt on the normals, projected to respect the equality
constraints; it is computed without gradient.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from diffcontact.contact.detect import ContactSet
from diffcontact.contact.effective_mass import effective_inverse_inertia
from diffcontact.dynamics.constraints import Constraints
from diffcontact.dynamics.inertia import inverse_factor_blocks
from diffcontact.solver.contact_solver import ContactSolver
from diffcontact.solver.policy import POLICY
from diffcontact.state import Params
from diffcontact.threads import one_thread

if TYPE_CHECKING:
    from diffcontact.systems.base import System

#: The penetration compensation of a task file without ``contact.compensation``: 1/8 of depth/dt (published).
COMPENSATION = 0.125
#: The dtype of a contact event's problems, whatever the state's: A = J_C M̂⁻¹J_Cᵀ assembled in float32 loses its
#: small eigenvalues where its rows differ in scale (a noisy rope's links compressed to almost nothing: diagonal up to
#: 7e7, least eigenvalue 0.13), and the impulses and their gradients then follow the rounding, not the model.
WIDE = torch.float64
#: Where an eigenvalue of that A is rounding (a flat direction), relative to its diagonal, for a system without joints:
#: its flat directions are exact (more contacts than degrees of freedom, whatever the positions), so A, assembled in
#: float64, is flat only to float64's rounding, far below the solver's default for a float64 input (1e-6), and an
#: eigenvalue between the two is real (a rope's nearly coincident nodes).  Systems with joints keep the default: their
#: joints hold only to the state's rounding and the integrator's drift (a gyroscope's rim contact then misses the
#: line to its pivot), so that their flat directions come out at that level.
FLAT_TOL = POLICY.wide_flat_tol


@dataclass(frozen=True)
class Phases:
    """One contact event's problems and impulses, per colliding element (B') and contact (K_c, d_c rows each).

    A: (B', C, C) contact-space inverse inertia; v_before: (B', C) contact velocity before; f_c, f_r: (B', C)
    impulses of compression and restitution; mu: (B', K_c) friction used; lower: (B', K_c) restitution bound
    e·f_c,n; MhJt: (B', D, C) M̂⁻¹J_Cᵀ (velocity change per impulse).
    Float64 whatever the state's dtype (:data:`WIDE`).
    """

    A: torch.Tensor
    v_before: torch.Tensor
    f_c: torch.Tensor
    f_r: torch.Tensor
    mu: torch.Tensor
    lower: torch.Tensor
    MhJt: torch.Tensor

    def velocity_change(self) -> torch.Tensor:
        """M̂⁻¹J_Cᵀ(f_c + f_r): (B', D) the velocity jump of the event, float64."""
        return (self.MhJt @ (self.f_c + self.f_r)[..., None])[..., 0]


@dataclass(frozen=True)
class ContactModel:
    """CM (``reg = 0``) or CMr (``reg > 0``, 1/kg), with penetration compensation ``compensation`` × depth/dt.

    ``lift``: how the normal targets become contact velocities (:meth:`target_velocity`): "pseudo-inverse" (the
    published Eq. S.18) or "effective-mass" (the motion of least kinetic energy that meets them).

    ``solver``: the :class:`~diffcontact.solver.ContactSolver` of both phases (tolerances, failure policy,
    counters); the default raises on a failed problem (no silent zero impulses).  The task's contact model is
    built by :func:`diffcontact.simulator.simulator_for`.
    """

    reg: float = 0.0
    compensation: float = COMPENSATION
    solver: ContactSolver = field(default_factory=ContactSolver)
    lift: str = "pseudo-inverse"

    def phases(
        self,
        constraints: Constraints,
        params: Params,
        x: torch.Tensor,
        v: torch.Tensor,
        contacts: ContactSet,
        dt: float,
    ) -> Phases:
        """Both phases' problems and impulses for the colliding elements (see :class:`Phases`)."""
        solve = self.solver
        idx, dc = contacts.index, contacts.dc
        xs, vs = x[idx].to(WIDE), v[idx].to(WIDE)
        Bp = xs.shape[0]
        Jc = contacts.J.to(xs)
        MhJt, A = effective_inverse_inertia(inverse_factor_blocks(params.inertia).to(WIDE), constraints, xs, Jc)
        A_qp = A + self.reg * torch.eye(A.shape[-1], dtype=A.dtype, device=A.device) if self.reg > 0 else A
        mu = params.mu.to(xs)[contacts.slot]
        mu = torch.where(contacts.frictionless.to(x.device), torch.zeros_like(mu), mu)
        e = params.e.to(xs)[contacts.slot]
        vC = (Jc @ vs.reshape(Bp, -1, 1))[..., 0]
        flat_tol = None if constraints.count else FLAT_TOL
        f_c = solve(A_qp, vC, mu, None, contacts.active, flat_tol=flat_tol)
        v_target = self.target_velocity(constraints, xs, contacts, dt, A)
        vC_c = vC + (A @ f_c[..., None])[..., 0]
        lower = e * f_c[:, ::dc]
        # a separating contact's compression impulse is zero up to rounding (±1e-16): the bound must stay ≥ 0
        lower = lower.clamp_min(0.0)
        f_r = solve(A_qp, vC_c - v_target, mu, lower, contacts.active, flat_tol=flat_tol)
        return Phases(A=A, v_before=vC, f_c=f_c, f_r=f_r, mu=mu, lower=lower, MhJt=MhJt)

    @torch.no_grad()
    def target_velocity(
        self, constraints: Constraints, xs: torch.Tensor, contacts: ContactSet, dt: float, A: torch.Tensor | None = None
    ) -> torch.Tensor:
        """v*_C (B', C) of paper Eq. S.17: v_d = −compensation·gap/dt on normals (0 on tangents), made a velocity
        the constrained system can have.  "pseudo-inverse" (published): lifted by the pseudo-inverse of J_C (min-norm
        least squares in the point coordinates, Eq. S.18), projected onto J_E y = 0 and mapped back by J_C; the
        point coordinates' Euclidean norm is not the body's, so equal depths under a flat face can give a target
        that tilts it.  "effective-mass": A A⁺ v_d (A: (B', C, C) the contact-space inverse inertia), the contact
        velocity of the motion of least kinetic energy closest to v_d: equal depths lift a face straight up."""
        Bp, k_c = contacts.active.shape
        vd = torch.zeros(Bp, k_c, contacts.dc, dtype=xs.dtype, device=xs.device)
        vd[..., 0] = -self.compensation * contacts.gap.to(xs) / dt
        vd = vd.reshape(Bp, -1, 1)
        if self.lift == "effective-mass":
            if A is None:
                raise ValueError("the effective-mass lift needs A, the contact-space inverse inertia")
            A = A.detach().to(xs)
            regular, _ = _regular(A, A.diagonal(dim1=-2, dim2=-1) != 0)
            target = vd.clone()  # (A A⁺ = I on the rows in use where A is regular on them)
            if not bool(regular.all()):
                with one_thread():
                    lifted = torch.linalg.lstsq(A[~regular], vd[~regular], driver="gelsd").solution
                target[~regular] = A[~regular] @ lifted
            return target[..., 0]
        Jc = contacts.J.to(xs).detach()
        regular, L = _regular(Jc @ Jc.mT, (Jc != 0).any(-1))
        if not constraints.count and bool(regular.all()):
            return vd[..., 0]  # (J_C J_C⁺ = I on the rows in use where J_C has full row rank)
        y = torch.zeros(Bp, Jc.shape[-1], 1, dtype=xs.dtype, device=xs.device)  # J_C⁺ v_d, (B', D, 1)
        y[regular] = Jc[regular].mT @ torch.cholesky_solve(vd[regular], L[regular])
        if not bool(regular.all()):
            with one_thread():
                y[~regular] = torch.linalg.lstsq(Jc[~regular], vd[~regular], driver="gelsd").solution
        if constraints.count:
            JE = constraints.jac(xs)
            L = torch.linalg.cholesky(JE @ JE.mT)
            y = y - JE.mT @ torch.cholesky_solve(JE @ y, L)
        return (Jc @ y)[..., 0]

    def __call__(
        self, system: System, params: Params, x: torch.Tensor, v: torch.Tensor, dt: float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Apply the contact model to a batch of ``system`` at x, v (B, P, d) over a step of dt (s): returns
        (v⁺ (B, P, d), in_contact (B,) bool)."""
        contacts = system.detector.detect(x)
        flag = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        if contacts is None:
            return v, flag
        ph = self.phases(system.constraints, params, x, v, contacts, dt)
        dv = ph.velocity_change().reshape(v[contacts.index].shape).to(v)
        flag[contacts.index] = True
        return v.index_put((contacts.index,), v[contacts.index] + dv), flag


def _regular(G: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Which symmetric PSD G (B, n, n) are regular on their rows in use ``rows`` (B, n) (the others zero), far from the
    rank cut-off of a least-squares solver: (regular (B,) bool, L (B, n, n) the Cholesky factor of G with the mean
    diagonal on the rows not in use).  Regular means λ_min ≥ √eps·‖G‖_F, from the bound λ_min ≥ 1/‖L⁻¹‖_F²; where it
    holds, G G⁺ = I on the rows in use, and a Cholesky solve replaces a rank-revealing least squares (SVD), which
    cost 58 % of a simulated frame of a 200-node rope."""
    on = rows.to(G.dtype)
    mean = (G.diagonal(dim1=-2, dim2=-1) * on).sum(-1) / on.sum(-1).clamp_min(1.0)
    G = G + torch.diag_embed((1.0 - on) * mean[:, None])
    L, info = torch.linalg.cholesky_ex(G)
    regular = info == 0
    if bool(regular.any()):
        eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device).expand(int(regular.sum()), -1, -1)
        inverse = torch.linalg.solve_triangular(L[regular], eye, upper=False)
        bound = 1.0 / inverse.square().sum((-2, -1))
        floor = torch.finfo(G.dtype).eps ** 0.5 * torch.linalg.matrix_norm(G[regular])
        regular[regular.clone()] = torch.isfinite(bound) & (bound >= floor)
    return regular, L
