"""Time of impact (TOI): contacts resolved at the instant their gap reaches zero inside a step.

The published scheme (paper Algorithm 1) detects contacts at the end of a step and resolves them there with a
velocity jump plus penetration compensation; neither the state nor its derivative then depends on when, inside
the step, the contact began (Zhong, Han, Dey, Brikis, L4DC 2023). Here, for each batch element, a step of
length h from (x, v) runs as a short sequence of events:

1. flow over the remaining time to the end of the step;
2. candidates: contacts with gap >= 0 at the start of the interval and < 0 at its end (a contact touching at
   the start, gap in [−tol, tol] (rounding), counts only if it approaches: ġ·remaining < −tol);
3. the earliest by linear interpolation of the gap, then its fraction s of the interval by safeguarded Newton on
   g(s) = gap(flow(x, v, s·L)) (bracket [0, 1], bisection where Newton leaves it), so that the gap of the
   flowed state is zero;
4. gradient: the impact time τ = s·L moves by δτ = −g/ġ from the last Newton point (held constant there), so
   that dτ/dθ = −g_θ/ġ (implicit function theorem; zero where |ġ·L| <= tol, i.e. a grazing contact), and the
   state moves with it to first order, (x, v) + δτ·(ẋ, v̇): one evaluation of the vector field instead of a
   second flow (δτ is the Newton residual's, below 1e-12 s in float64, so the values are those of a flow to τ);
5. resolve every contact with gap < tol at the impact (the earliest always) with the same ContactModel (both
   convex problems; the penetration target only sees negative gaps), then go on.

At most ``max_events`` events per step and one per contact (a contact that comes back within the same step, e.g. a
rope limit chattering under its spring with e = 0, is not re-timed); whatever still penetrates at the end of the
step (resting contacts, contacts already penetrating at the start, events beyond the bounds) is resolved there by
the published scheme.
Elements are handled with masks and index tensors: no Python loop over samples or contacts.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch

from diffcontact.contact.detect import Detector
from diffcontact.contact.impulse import ContactModel
from diffcontact.state import Params

if TYPE_CHECKING:
    from diffcontact.systems.base import System

Flow = Callable[[torch.Tensor, torch.Tensor, float | torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""The smooth flow (x, v, dt) -> (x, v) at t + dt; dt a float or a tensor (B, 1, 1) in s."""
Rate = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""The smooth vector field (x, v) -> (ẋ, v̇) of the flow, each (B, P, d)."""

MAX_EVENTS = 8
NEWTON_ITERS = 12


def event_tol(dtype: torch.dtype) -> float:
    """Gap tolerance (units of the gap) below which a contact counts as touching: 1e-9 in float64."""
    return max(1e-9, 100 * torch.finfo(dtype).eps)


def impact_fraction(
    flow: Flow, detector: Detector, x: torch.Tensor, v: torch.Tensor, L: torch.Tensor, k: torch.Tensor, s0: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Root s in [0, 1] of g(s) = gap_k(flow(x, v, s L)) for elements whose gap k goes from >= 0 to < 0.

    x, v (B, P, d); L (B,) interval length in s; k (B,) candidate index; s0 (B,) first guess. Returns s (B,),
    the flowed state (x, v) at s, and g_s = ġ L (B,) there. Safeguarded Newton, at most NEWTON_ITERS flows. The
    flows run with gradients as outside, at times s L held constant: the state returned is connected to x, v and
    the flow's parameters (so the caller need not flow to the root again); s and g_s are not.
    """
    atol = 64 * torch.finfo(x.dtype).eps
    L, s0 = L.detach(), s0.detach()
    lo, hi = torch.zeros_like(s0), torch.ones_like(s0)
    s = s0.clamp(0.0, 1.0)
    xr = vr = slope = None  # (set by the first iteration)
    for it in range(NEWTON_ITERS):
        xr, vr = flow(x, v, (s * L)[:, None, None])
        with torch.no_grad():
            g, rate = detector.rates(xr.detach(), vr.detach())
            g, slope = g.gather(1, k[:, None])[:, 0], rate.gather(1, k[:, None])[:, 0] * L
            done = g.abs() <= atol
            lo, hi = torch.where(g >= 0, s, lo), torch.where(g < 0, s, hi)
            newton = s - g / slope
            ok = (slope < 0) & (newton > lo) & (newton < hi)
            s_next = torch.where(done, s, torch.where(ok, newton, 0.5 * (lo + hi)))
        if bool((s_next == s).all()) or it == NEWTON_ITERS - 1:  # converged, or return the last point evaluated
            break
        s = s_next
    if xr is None or vr is None or slope is None:
        raise ValueError(f"NEWTON_ITERS = {NEWTON_ITERS} is not >= 1")
    return s, xr, vr, slope


def impact_state(
    flow: Flow,
    rate: Rate,
    detector: Detector,
    x: torch.Tensor,
    v: torch.Tensor,
    L: torch.Tensor,
    k: torch.Tensor,
    s0: torch.Tensor,
    tol: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The time τ (B,) in s at which gap k (B,) of the flow from x, v (B, P, d) reaches zero within L (B,) s, and the
    state (x, v) there, first guess s0 (B,) of τ / L (:func:`impact_fraction`). With gradients enabled, τ and the
    state carry dτ/dθ = −g_θ / ġ: one Newton step at the root with ġ held constant (0 where |ġ L| <= tol, a grazing
    contact), the state moved with it to first order, (x, v) + δτ·(ẋ, v̇) with ``rate`` the flow's vector field."""
    s, xc, vc, slope = impact_fraction(flow, detector, x, v, L, k, s0)
    tau = s * L.detach()
    if torch.is_grad_enabled():
        g = detector.gaps(xc).gather(1, k[:, None])[:, 0]
        ok = slope < -tol
        shift = torch.where(ok, -g * L.detach() / torch.where(ok, slope, -1.0), torch.zeros_like(g))
        xd, vd = rate(xc, vc)
        xc, vc, tau = xc + shift[:, None, None] * xd, vc + shift[:, None, None] * vd, tau + shift
    return tau, xc, vc


def toi_step(
    flow: Flow,
    rate: Rate,
    model: ContactModel,
    system: System,
    params: Params,
    x: torch.Tensor,
    v: torch.Tensor,
    dt: float,
    max_events: int = MAX_EVENTS,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One step of length dt (s) of ``system`` from x, v (B, P, d) with contacts at their time of impact; ``rate``
    the vector field that ``flow`` integrates.

    Returns (x, v) at t + dt and in_contact (B,) bool (an event or an end-of-step contact).
    """
    B, detector = x.shape[0], system.detector
    tol = event_tol(x.dtype)
    x1, v1 = flow(x, v, dt)
    rem = x.new_full((B,), dt)  # time left in the step (s); carries ds/dθ after an event
    hit = x.new_zeros(B, dtype=torch.bool)
    resolved = x.new_zeros(B, detector.count, dtype=torch.bool)  # contacts that had their event in this step
    for _ in range(max_events):
        g0, r0 = detector.rates(x, v)
        with torch.no_grad():
            g1 = detector.gaps(x1)
            cand = (g1 < 0) & (g0 >= -tol) & ((g0 > tol) | (r0 * rem.detach()[:, None] < -tol)) & ~resolved
            rows = torch.nonzero(cand.any(1)).flatten()
        if rows.numel() == 0:
            break
        with torch.no_grad():
            a, b, c = g0[rows], g1[rows], cand[rows]
            ahead = c & (a > 0)  # a touching candidate (gap in [−tol, 0]) starts at s = 0
            frac = torch.where(ahead, a / torch.where(ahead, a - b, 1.0), torch.where(c, 0.0, torch.inf))
            s0, k = frac.min(dim=1)
        xs, vs, L = x[rows], v[rows], rem[rows]
        tau, xc, vc = impact_state(flow, rate, detector, xs, vs, L, k, s0, tol)
        with torch.no_grad():
            gc = detector.gaps(xc)
            mark = (gc < tol) | torch.nn.functional.one_hot(k, gc.shape[1]).bool()
        contacts = detector.select(xc, mark, gc.clamp_max(0.0))
        if contacts is None:  # (unreachable: every row marks its event's candidate k)
            raise AssertionError("no contact at a time of impact")
        ph = model.phases(system.constraints, params, xc, vc, contacts, dt)
        vc = vc + ph.velocity_change().reshape(vc.shape).to(vc)
        L_after = L - tau
        xe, ve = flow(xc, vc, L_after[:, None, None])
        x, v = x.index_put((rows,), xc), v.index_put((rows,), vc)
        x1, v1 = x1.index_put((rows,), xe), v1.index_put((rows,), ve)
        rem = rem.index_put((rows,), L_after)
        hit[rows] = True
        resolved[rows, k] = True
    v1, end_hit = model(system, params, x1, v1, dt)
    return x1, v1, hit | end_hit
