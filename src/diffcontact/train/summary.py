"""What a training run learned, against the truth, with what the data can tell (``learned.json``).

A contact slot's e is identifiable only if the training chunks have contacts of that slot, and its μ only if some of
those contacts have a tangential direction (the rope's bend and stretch limits are one-dimensional: μ acts on
nothing).  Errors are taken over the identifiable slots; the others are reported as such, not as errors.

Inertia: with a learned potential the dynamics are unchanged when the kinetic and the potential energy are scaled
together, and only motions that obey the constraints carry kinetic energy.  So what the data identifies is the
mass matrix restricted to the constraints' tangent space, up to one factor: ``inertia_spread`` compares exactly
that.  Mass ratios follow from it where bodies move freely; single moments do not: a 2-D body's kinetic energy of
rotation holds only the sum of its two second moments, and the gyroscope on its joint holds only the ratios of
its principal moments about the joint (its per-axis second moments about the centre of mass are known up to
J → s·(J + r²) − r², r the joint-to-centre offset).
"""

from __future__ import annotations

import torch

from diffcontact.dynamics.inertia import body_blocks, dense
from diffcontact.state import Inertia
from diffcontact.systems.base import System


def slot_contacts(system: System, chunk_x: torch.Tensor, n_slots: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Contacts per slot in training chunks: (collisions, with_friction), each (n_slots,) int64.

    A collision is a chunk frame after the first (each follows one simulated step) at which a contact candidate
    of the slot is active, that is, at which the contact model solves for its impulse; with_friction counts
    those of candidates with tangential rows.  chunk_x: (N, L, P, d) positions in m.
    """
    det = system.detector
    collisions = torch.zeros(n_slots, dtype=torch.long)
    frictional = torch.zeros(n_slots, dtype=torch.long)
    if not det.kinds or chunk_x.shape[1] < 2:
        return collisions, frictional
    hit = det.gaps(chunk_x[:, 1:].flatten(0, 1).to(torch.float64)) < 0  # (N·(L−1), K_max)
    per_candidate = hit.sum(0)
    tangential = torch.cat([torch.full((k.count,), k.dc > 1) for k in det.kinds])
    collisions.index_add_(0, det.slot, per_candidate)
    frictional.index_add_(0, det.slot, per_candidate * tangential)
    return collisions, frictional


def inertia_spread(system: System, learned: Inertia, true: Inertia, x: torch.Tensor) -> dict:
    """The learned against the true mass matrix on the constraints' tangent space, up to a common factor.

    At each configuration x (B, P, d) (m), with T a basis of the velocities the constraints allow, the generalised
    eigenvalues λ of (Tᵀ M_learned T, Tᵀ M_true T) are the ratios learned/true of the kinetic energy of the
    principal motions; a model equal to the truth up to the scale its potential absorbs has all λ equal.
    Returns {"spread": max over x of λ_max/λ_min − 1, "scale": the median λ}.
    """
    d = system.d
    M_l = dense(body_blocks(Inertia(learned.masses.detach().double(), learned.moments.detach().double()))[0], d)
    M_t = dense(body_blocks(Inertia(true.masses.double(), true.moments.double()))[0], d)
    x = x.to(torch.float64)
    Je = system.constraints.jac(x)  # (B, E, D)
    D = M_t.shape[-1]
    if Je.shape[1]:
        _, sv, Vh = torch.linalg.svd(Je)  # (the null space: right singular vectors beyond the rank)
        rank = int((sv > 1e-9 * sv[:, :1]).sum(-1).max())
        T = Vh[:, rank:].mT  # (B, D, D − rank)
    else:
        T = torch.eye(D, dtype=torch.float64).expand(x.shape[0], D, D)
    Mt, Ml = T.mT @ M_t @ T, T.mT @ M_l @ T
    L = torch.linalg.cholesky(Mt)
    W = torch.linalg.solve_triangular(L, torch.linalg.solve_triangular(L, Ml, upper=False).mT, upper=False)
    lam = torch.linalg.eigvalsh(0.5 * (W + W.mT))  # (B, n)
    return {"spread": float((lam[:, -1] / lam[:, 0]).max() - 1), "scale": float(lam.median())}


def compare(learned: torch.Tensor, true: torch.Tensor, identifiable: torch.Tensor | None = None) -> dict:
    """``{"learned", "true", "max_abs_error"[, "identifiable"]}``: the error over the identifiable entries (None
    where there is none)."""
    out = {"learned": learned.tolist(), "true": true.tolist()}
    err = (learned - true).abs()
    if identifiable is not None:
        err = err[identifiable]
        out["identifiable"] = identifiable.tolist()
    out["max_abs_error"] = float(err.max()) if err.numel() else None
    return out


def learned_summary(net, task, chunk_x: torch.Tensor) -> dict:
    """``{"mu", "e", "mass_ratio"[, "moments"], "inertia", "collisions", "collisions_with_friction"}`` of a model
    ``net`` (its ``params``: LearnedParams) trained on ``task``'s chunks ``chunk_x`` (N, L, P, d).

    μ and e per contact slot, with the slots the data can identify (homogeneous tasks share one value, identifiable
    if any slot is); mass ratio = mass / mass of the first body; moments (extended bodies only): second moments per
    unit mass in m², body by body and axis by axis (see the module docstring for what of them is identifiable);
    inertia: ``inertia_spread``, what is.
    """
    truth, learned = task.params, net.params
    n_slots = truth.mu.numel()
    collisions, frictional = slot_contacts(task.system, chunk_x, n_slots)
    seen_e, seen_mu = collisions > 0, frictional > 0
    if learned.homogeneous:  # (one shared value: identified by every slot's contacts)
        seen_e, seen_mu = seen_e.any().expand(n_slots), seen_mu.any().expand(n_slots)
    m_true = truth.inertia.masses.double()
    out = {
        "mu": compare(learned.mu.detach().double(), truth.mu.double(), seen_mu),
        "e": compare(learned.e.detach().double(), truth.e.double(), seen_e),
        "mass_ratio": compare(
            learned.inertia.masses.detach().double() / learned.inertia.masses[0].item(), m_true / m_true[0]
        ),
    }
    moments = truth.inertia.moments
    if moments.numel():
        out["moments"] = compare(learned.inertia.moments.detach().double().flatten(), moments.double().flatten())
    # (at the first frames of up to 64 chunks)
    out["inertia"] = inertia_spread(task.system, learned.inertia, truth.inertia, chunk_x[:64, 0].detach())
    out["collisions"] = collisions.tolist()
    out["collisions_with_friction"] = frictional.tolist()
    return out
