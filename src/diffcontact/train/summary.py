"""What a training run learned, against the truth, with what the data can tell (``learned.json``).

A contact slot's μ is identifiable only from collisions in which the contact slides (a sticking contact only
bounds μ from below; the rope's one-dimensional limits have no tangent at all), and its e only from collisions
whose restitution impulse the bound e·f_c,n sets (where the impulse toward the target velocity of the penetration
compensation exceeds it, any smaller e gives the same motion).  Errors are taken over the identifiable slots; the
others are reported as such, not as errors.

Inertia: with a learned potential the dynamics are unchanged when the kinetic and the potential energy are scaled
together, and only motions that obey the constraints carry kinetic energy.  So what the data identifies is the
mass matrix restricted to the constraints' tangent space, up to one factor: ``inertia_spread`` compares exactly
that.  Mass ratios follow from it where bodies move freely; single moments do not: a 2-D body's kinetic energy of
rotation holds only the sum of its two second moments, and the gyroscope on its joint holds only the ratios of
its principal moments about the joint (its per-axis second moments about the centre of mass are known up to
J_k → s·(J_k + r_k²) − r_k², r_k the joint-to-centre offset's component along axis k).
"""

from __future__ import annotations

from typing import Any

import torch

from diffcontact.dynamics.inertia import body_blocks, dense
from diffcontact.dynamics.potentials import Gravity, SumPotential
from diffcontact.models.params import LearnedGravity
from diffcontact.state import Inertia
from diffcontact.systems.base import System
from diffcontact.train.identify import evidence


def slot_contacts(task, chunk_x: torch.Tensor, chunk_v: torch.Tensor) -> dict[str, torch.Tensor]:
    """Collisions per slot in training chunks, and those that identify μ and e: each (n_slots,) int64.

    A collision is a chunk step (frame t − 1 to t) at which a contact candidate of the slot is active, that is, at
    which the contact model solves for its impulse.  Replaying the step with the true parameters (float64):
    ``slipping`` are those whose contact still slides tangentially after a phase with a nonzero impulse (only they
    fix μ; a sticking contact bounds it from below, a separating one says nothing), ``bound`` those whose
    restitution impulse is set by the bound e·f_c,n > 0 (only they fix e; elsewhere the impulse toward the target
    velocity exceeds it and e below that has no effect).  chunk_x, chunk_v: (N, L, P, d) in m and m/s.
    """
    from diffcontact.simulator import simulator_for

    n_slots = task.params.mu.numel()
    counts = {k: torch.zeros(n_slots, dtype=torch.long) for k in ("collisions", "slipping", "bound")}
    det = task.system.detector
    if not det.kinds or chunk_x.shape[1] < 2:
        return counts
    sim = simulator_for(task)
    x0, v0 = (c[:, :-1].flatten(0, 1).to(torch.float64) for c in (chunk_x, chunk_v))
    with torch.no_grad():
        x1, v1 = sim.flow(task.params, x0, v0, task.dt)
        contacts = det.detect(x1)
        if contacts is None:
            return counts
        ph = sim.contact_model.phases(task.system.constraints, task.params, x1, v1, contacts, task.dt)
    dc, (B, K) = contacts.dc, contacts.active.shape
    active = contacts.active
    scale = ph.v_before.abs().amax(-1, keepdim=True).clamp_min(1e-12)  # (B', 1) m/s

    def slides(f, q):  # (B', K): an impulse that leaves the contact sliding, ‖(A f + q)_t‖ > 0
        g = ((ph.A @ f[..., None])[..., 0] + q).view(B, K, dc)[..., 1:]
        f_n = f.view(B, K, dc)[..., 0]
        return (f_n > 1e-9 * f_n.amax().clamp_min(1e-300)) & (g.norm(dim=-1) > 1e-6 * scale)

    slipping = torch.zeros_like(active)
    if dc > 1:
        after_c = ph.v_before + (ph.A @ ph.f_c[..., None])[..., 0]
        slipping = active & ~contacts.frictionless & (slides(ph.f_c, ph.v_before) | slides(ph.f_r, after_c))
    f_rn = ph.f_r.view(B, K, dc)[..., 0]
    bound = active & (ph.lower > 1e-9 * ph.lower.amax().clamp_min(1e-300)) & (f_rn <= ph.lower * (1 + 1e-6))
    for key, mask in (("collisions", active), ("slipping", slipping), ("bound", bound)):
        counts[key].index_add_(0, contacts.slot[mask], torch.ones(int(mask.sum()), dtype=torch.long))
    return counts


def inertia_spread(system: System, learned: Inertia, true: Inertia, x: torch.Tensor) -> dict:
    """The learned against the true mass matrix on the constraints' tangent space, up to a common factor.

    At each configuration x (B, P, d) (m), with T a basis of the velocities the constraints allow, the generalised
    eigenvalues λ of (Tᵀ M_learned T, Tᵀ M_true T) are the ratios learned/true of the kinetic energy of the
    principal motions; a model equal to the truth up to the scale its potential absorbs has all λ equal.
    Returns {"spread": max over x of λ_max/λ_min − 1, "scale": the median λ}.
    """

    def as_double(i: Inertia) -> Inertia:
        com = None if i.com is None else i.com.detach().double()
        return Inertia(i.masses.detach().double(), i.moments.detach().double(), com)

    d = system.d
    M_l = dense(body_blocks(as_double(learned))[0], d)
    M_t = dense(body_blocks(as_double(true))[0], d)
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
    out: dict[str, Any] = {"learned": learned.tolist(), "true": true.tolist()}
    err = (learned - true).abs()
    if identifiable is not None:
        err = err[identifiable]
        out["identifiable"] = identifiable.tolist()
    out["max_abs_error"] = float(err.max()) if err.numel() else None
    return out


def learned_summary(net, task, chunk_x: torch.Tensor, chunk_v: torch.Tensor, noise: float = 0.0) -> dict:
    """``{"mu", "e", "mass_ratio"[, "moments", "centre_of_mass"], "inertia", "collisions", "collisions_slipping",
    "collisions_bound", "evidence_chunks"}`` of a model ``net`` (its ``params``: LearnedParams) trained on
    ``task``'s chunks ``chunk_x``, ``chunk_v`` (N, L, P, d), recorded with observation noise ``noise`` (0: none).

    μ and e also carry what the learned model alone says of them (:mod:`diffcontact.train.identify`), per slot:
    ``std_error`` (None: the data do not fix it), ``bootstrap_error`` (on noisy data: the bias and spread of a refit
    at that noise; None without noise), ``identified`` (a 95 % interval within ± 0.01) and
    ``max_abs_error_identified`` (against the truth, over the slots so marked); ``evidence_chunks``: the training
    chunks with a collision of each slot under the learned model.

    μ and e per contact slot, with the slots the data can identify (``slot_contacts``: μ by slipping collisions,
    e by collisions whose restitution the bound e·f_c,n sets, or, for a true e of 0, by any collision; homogeneous
    tasks share one value, identifiable if any slot is); mass ratio = mass / mass of the first body; moments
    (extended bodies only): second moments per unit mass in m², body by body and axis by axis (see the module
    docstring for what of them is identifiable); centre_of_mass (the box): in m, body frame, from its centre;
    inertia: ``inertia_spread``, what is; g (m/s², with ``g_learned``): the gravity of a learned-gravity potential,
    or of the task's own potential where it is given and holds one.
    """
    from diffcontact.models.baselines import Baseline

    if isinstance(net, Baseline):
        return baseline_summary(net, task, chunk_x)
    truth, learned = task.params, net.params
    n_slots = truth.mu.numel()
    counts = slot_contacts(task, chunk_x, chunk_v)
    seen_mu = counts["slipping"] > 0
    seen_e = (counts["bound"] > 0) | ((truth.e == 0) & (counts["collisions"] > 0))
    if learned.homogeneous:  # (one shared value: identified by every slot's contacts)
        seen_e, seen_mu = seen_e.any().expand(n_slots), seen_mu.any().expand(n_slots)
    m_true = truth.inertia.masses.double()
    m_learned = learned.inertia.masses.detach().double()
    out: dict[str, Any] = {
        "mu": compare(learned.mu.detach().double(), truth.mu.double(), seen_mu),
        "e": compare(learned.e.detach().double(), truth.e.double(), seen_e),
        "mass_ratio": compare(m_learned / m_learned[0], m_true / m_true[0]),
    }
    found = evidence(net, chunk_x, chunk_v, noise=noise)  # (judged from the learned model alone: train/identify.py)
    per_slot = [0] * n_slots if learned.homogeneous else list(range(n_slots))
    for key in ("mu", "e"):
        se, boot, ok = (found[key][k] for k in ("std_error", "bootstrap_error", "identified"))
        out[key]["std_error"] = [se[c] for c in per_slot]
        out[key]["bootstrap_error"] = [boot[c] for c in per_slot]
        out[key]["identified"] = [ok[c] for c in per_slot]
        err = [abs(a - b) for a, b, c in zip(out[key]["learned"], out[key]["true"], per_slot) if ok[c]]
        out[key]["max_abs_error_identified"] = max(err) if err else None
    out["evidence_chunks"] = [found["chunks"][c] for c in per_slot]
    out |= inertia_items(learned.inertia, truth.inertia)
    # (at the first frames of up to 64 chunks)
    out["inertia"] = inertia_spread(task.system, learned.inertia, truth.inertia, chunk_x[:64, 0].detach())
    if isinstance(learned.potential, LearnedGravity):
        out["g"], out["g_learned"] = float(learned.potential.g.detach()), True
    elif isinstance(learned.potential, SumPotential):  # (the task's own potential, given: its gravity if it has one)
        given = [t.g for t in learned.potential.terms if isinstance(t, Gravity)]
        if len(given) == 1:
            out["g"], out["g_learned"] = float(given[0]), False
    out["collisions"] = counts["collisions"].tolist()
    out["collisions_slipping"] = counts["slipping"].tolist()
    out["collisions_bound"] = counts["bound"].tolist()
    return out


def inertia_items(learned: Inertia, truth: Inertia) -> dict:
    """``{"moments"[, "centre_of_mass"]}`` of a learned inertia against the true one (``compare``), where the bodies
    have moments (extended bodies: m² per unit mass) and a centre of mass off their first point (the box: m, body
    frame, from its centre)."""
    out = {}
    if truth.moments.numel():
        out["moments"] = compare(learned.moments.detach().double().flatten(), truth.moments.double().flatten())
    if truth.com is not None and learned.com is not None:
        out["centre_of_mass"] = compare(learned.com.detach().double().flatten(), truth.com.double().flatten())
    return out


def against_nominal(summary: dict) -> dict:
    """A summary (:func:`learned_summary`) of a model fitted to measured data, whose task holds nominal values on
    record, not a truth: each compared item's "true" becomes "nominal" and its "max_abs_error" "max_abs_from_nominal"
    (no "max_abs_error_identified"); the inertia's "spread" and "scale" are from the nominal inertia."""
    out = dict(summary)
    for key, item in summary.items():
        if isinstance(item, dict) and "true" in item:
            renamed = {"true": "nominal", "max_abs_error": "max_abs_from_nominal"}
            out[key] = {renamed.get(k, k): v for k, v in item.items() if k != "max_abs_error_identified"}
    if "inertia" in out:
        out["inertia"] = {**out["inertia"], "against": "nominal"}
    return out


def baseline_summary(net, task, chunk_x: torch.Tensor) -> dict:
    """What a baseline learned (``learned.json``): ``{"model", "weights"[, "mass_ratio"[, "moments"[,
    "centre_of_mass"]]], "inertia"}``.

    The inertia parts (as in :func:`learned_summary`) where the baseline has a learned CLNN (MLP-CD-CLNN,
    IN-CP-CLNN); no μ or e (the baselines do not learn them: IN-CP-* are given the true ones).  IN-CP-SP learns no
    physical parameter: its "inertia" is that of the true inertia it is given (``"given": true``).  ``weights``: the
    number of trained scalars.  chunk_x: (N, L, P, d) training chunks in m.
    """
    out = {"model": net.name, "weights": sum(p.numel() for p in net.parameters())}
    learned, truth = net.params, task.params
    if learned is None:
        out["inertia"] = {**inertia_spread(task.system, truth.inertia, truth.inertia, chunk_x[:64, 0]), "given": True}
        return out
    m_learned, m_true = learned.inertia.masses.detach().double(), truth.inertia.masses.double()
    out["mass_ratio"] = compare(m_learned / m_learned[0], m_true / m_true[0])
    out |= inertia_items(learned.inertia, truth.inertia)
    out["inertia"] = inertia_spread(task.system, learned.inertia, truth.inertia, chunk_x[:64, 0].detach())
    return out
