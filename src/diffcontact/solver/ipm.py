"""Batched primal-dual interior-point method for many small contact cone QPs (no autograd).

Standard form, per batch element (all contacts of dimension d, K contacts, n = K·d variables):

    minimise ½ zᵀPz + cᵀz   subject to   z_n,i ≥ l_i  and  ‖z_t,i‖ ≤ z_n,i   for every active contact i,

i.e. G z + s = h with s in the product of K non-negative rays and (if d ≥ 2) K second-order cones, where
G z = (−z_n,i ; −z_i) and h = (−l_i ; 0).  Inactive contacts have no cones and P = I, c = 0 there, so z = 0.

The method is Mehrotra's predictor–corrector with Nesterov–Todd scaling (as in CVXOPT's coneqp).  The
reduced Newton matrix H = P + GᵀW⁻²G is P plus a d×d block per contact; it is positive definite even when P is
singular, and one Cholesky factor serves both directions of an iteration.  Each batch element stops on its
own; the loop ends when all are done.  The final factor is returned for the implicit backward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffcontact.solver import cones

CONVERGED, INACCURATE, MAX_ITER, NUMERICAL, UNBOUNDED = 0, 1, 2, 3, 4


@dataclass
class IPMResult:
    """Solution and the data the backward pass needs.  Shapes: B batch, K contacts, n = K·d."""

    z: torch.Tensor  # (B, n)
    status: torch.Tensor  # (B,) int64, codes above
    iterations: torch.Tensor  # (B,) int64
    residual: torch.Tensor  # (B,) max of primal, dual residual and complementarity
    chol: torch.Tensor  # (B, n, n) Cholesky factor of H at the solution
    w2_lin: torch.Tensor  # (B, K) W⁻² of the non-negative rays (λ/s), 0 for inactive contacts


class _Cones:
    """Slack and dual of every cone, with the masks that switch inactive contacts off."""

    def __init__(self, s_l, lam_l, s_q, lam_q, on_l, on_q):
        self.s_l, self.lam_l, self.s_q, self.lam_q, self.on_l, self.on_q = s_l, lam_l, s_q, lam_q, on_l, on_q

    def gap(self) -> torch.Tensor:
        g = self.on_l * self.s_l * self.lam_l
        if self.s_q is not None:
            g = g + self.on_q * (self.s_q * self.lam_q).sum(-1)
        return g.sum(-1)


def _block_index(K: int, d: int, device) -> torch.Tensor:
    """Flat indices into an (n, n) matrix of the K diagonal d×d blocks, ordered (k, i, j)."""
    n = K * d
    k = torch.arange(K, device=device).view(K, 1, 1)
    i = torch.arange(d, device=device).view(1, d, 1)
    j = torch.arange(d, device=device).view(1, 1, d)
    return ((k * d + i) * n + (k * d + j)).reshape(-1)


def _cholesky(H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched Cholesky; elements that fail get a small diagonal shift, then are flagged if still failing."""
    L, info = torch.linalg.cholesky_ex(H)
    bad = info != 0
    if bad.any():
        scale = H.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1.0)
        eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
        shift = (1e-13 * scale)[:, None, None] * eye
        L2, info2 = torch.linalg.cholesky_ex(H + shift * bad[:, None, None])
        L = torch.where(bad[:, None, None], L2, L)
        bad = info2 != 0
    return L, bad


def solve_ipm(
    P: torch.Tensor,
    c: torch.Tensor,
    lower: torch.Tensor,
    on: torch.Tensor,
    d: int,
    *,
    tol: float = 1e-10,
    acceptable_tol: float = 1e-7,
    max_iter: int = 60,
    trace: list | None = None,
) -> IPMResult:
    """Solve the batch in standard form (see module docstring).

    P: (B, n, n) symmetric PSD; c: (B, n); lower: (B, K) ≥ 0; on: (B, K) bool; float64.
    The data are expected scaled to order one (see ``problem.py``); ``tol`` is absolute on that scale.
    """
    B, n = c.shape
    K = n // d
    dt, dev = P.dtype, P.device
    onf = on.to(dt)
    # With a zero lower bound the ray z_n ≥ 0 is implied by the second-order cone; dropping it keeps the
    # multipliers unique at separating (apex) contacts.
    on_l = on & (lower > 0) if d >= 2 else on
    onl = on_l.to(dt)
    soc = d >= 2
    blk = _block_index(K, d, dev)
    eye_d = torch.eye(d, dtype=dt, device=dev)
    e_n = torch.zeros(d, dtype=dt, device=dev)
    e_n[0] = 1.0
    lin_block = e_n[:, None] * e_n[None, :]

    def Gz(z):  # (B, n) -> linear (B, K), soc (B, K, d)
        zk = z.view(B, K, d)
        return -onl * zk[..., 0], (-onf[..., None] * zk if soc else None)

    def GTy(y_l, y_q):  # -> (B, n)
        out = torch.zeros(B, K, d, dtype=dt, device=dev)
        out[..., 0] = -onl * y_l
        if soc:
            out = out - onf[..., None] * y_q
        return out.view(B, n)

    h_l = -onl * lower

    def assemble(w2_l, w2_q):
        """H = P + GᵀW⁻²G as P plus one d×d block per contact."""
        blocks = (onl * w2_l)[..., None, None] * lin_block
        if soc:
            blocks = blocks + onf[..., None, None] * w2_q
        H = P.reshape(B, n * n).clone()
        H[:, blk] += blocks.reshape(B, K * d * d)
        return H.view(B, n, n)

    # ---- initial point: solve with W = I, then shift slacks and duals into the cones (CVXOPT) ----
    H0 = assemble(torch.ones(B, K, dtype=dt, device=dev), eye_d.expand(B, K, d, d) if soc else None)
    L0, _ = _cholesky(H0)
    rhs0 = -c + GTy(h_l, torch.zeros(B, K, d, dtype=dt, device=dev) if soc else None)
    z = torch.cholesky_solve(rhs0.unsqueeze(-1), L0).squeeze(-1)
    gz_l, gz_q = Gz(z)
    s_l = h_l - gz_l
    s_q = -gz_q if soc else None
    lam_l, lam_q = -s_l, (-s_q if soc else None)

    def shift(x_l, x_q):
        m = torch.where(on_l, x_l, torch.full_like(x_l, float("inf")))
        if soc:
            m = torch.minimum(m, torch.where(on, cones.soc_min_eig(x_q), torch.full_like(x_l, float("inf"))))
        worst = -m.amin(-1)
        worst = torch.where(torch.isfinite(worst), worst, torch.zeros_like(worst))
        add = torch.where(worst >= -1e-8, 1.0 + worst, torch.zeros_like(worst))[:, None]
        x_l = torch.where(on_l, x_l + add, torch.ones_like(x_l))
        if soc:
            ident = cones.soc_identity((B, K), d, x_l)
            x_q = torch.where(on[..., None], x_q + add[..., None] * ident, ident)
        return x_l, x_q

    s_l, s_q = shift(s_l, s_q)
    lam_l, lam_q = shift(lam_l, lam_q)
    if soc:
        # The SOC scaling is kept as general matrices W (λ̃ = Wλ = W⁻ᵀs) and updated multiplicatively from the
        # well-centred scaled iterates, which avoids the cancellation of x0² − ‖x1‖² near the cone boundary.
        Wq, Wq_inv = cones.SocNTScaling(s_q, lam_q).matrices()
        lt_q = (Wq @ lam_q.unsqueeze(-1)).squeeze(-1)
    else:
        Wq = Wq_inv = lt_q = None

    degree = (onl + (onf if soc else 0.0)).sum(-1).clamp_min(1.0)
    status = torch.full((B,), MAX_ITER, dtype=torch.long, device=dev)
    done = ~on.any(-1)  # nothing to solve
    status[done] = CONVERGED
    iterations = torch.zeros(B, dtype=torch.long, device=dev)
    best = {"res": torch.full((B,), float("inf"), dtype=dt, device=dev), "age": torch.zeros(B, dtype=torch.long)}

    def keep_best(improved, **cur):
        for k, v in cur.items():
            if v is None:
                continue
            if k not in best:
                best[k] = v.clone()
            else:
                m = improved.view(-1, *([1] * (v.dim() - 1)))
                best[k] = torch.where(m, v, best[k])

    def residuals(z, s_l, lam_l, s_q, lam_q):
        r_z = (P @ z.unsqueeze(-1)).squeeze(-1) + c + GTy(lam_l, lam_q)
        gz_l, gz_q = Gz(z)
        r_l = onl * (gz_l + s_l - h_l)
        r_q = onf[..., None] * (gz_q + s_q) if soc else None
        return r_z, r_l, r_q

    def mv(M, x):
        return (M @ x.unsqueeze(-1)).squeeze(-1)

    for it in range(max_iter + 1):
        r_z, r_l, r_q = residuals(z, s_l, lam_l, s_q, lam_q)
        gap = _Cones(s_l, lam_l, s_q, lam_q, onl, onf).gap()
        pres = r_l.abs().amax(-1)
        if soc:
            pres = torch.maximum(pres, r_q.abs().amax((-1, -2)))
        dres = r_z.abs().amax(-1)
        # KKT residual relative to the size of the solution (the data are scaled to order one)
        res = torch.maximum(torch.maximum(pres, dres), gap) / z.abs().amax(-1).clamp_min(1.0)
        if trace is not None:
            trace.append((pres.clone(), dres.clone(), gap.clone()))
        finite = torch.isfinite(res) & torch.isfinite(z).all(-1)
        improved = ~done & finite & (res < best["res"])
        best["age"] = torch.where(improved, torch.zeros_like(best["age"]), best["age"] + 1)
        best["res"] = torch.where(improved, res, best["res"])
        keep_best(improved, z=z, s_l=s_l, lam_l=lam_l, s_q=s_q, lam_q=lam_q, Wq=Wq, Wq_inv=Wq_inv)
        conv = ~done & finite & (res <= tol)
        status[conv] = CONVERGED
        unbounded = ~done & finite & (z.abs().amax(-1) > 1e12)
        status[unbounded] = UNBOUNDED
        # stop an element that stalls (no improvement for 5 iterations) or breaks down; its best iterate is kept
        stalled = ~done & ~conv & ((best["age"] >= 5) | ~finite)
        done = done | conv | unbounded | stalled
        if bool(done.all()) or it == max_iter:
            break
        iterations = iterations + (~done).long()
        run = ~done

        # ---- scaling and the Newton matrix H = P + GᵀW⁻¹W⁻ᵀG ----
        w2_l = lam_l / s_l
        lt_l = (s_l * lam_l).sqrt()  # λ̃ of the rays; W of a ray is √(s/λ) = s/λ̃
        w2_q = Wq_inv @ Wq_inv.mT if soc else None
        L, bad = _cholesky(assemble(w2_l, w2_q))
        status[run & bad] = NUMERICAL
        done = done | (run & bad)
        run = ~done

        def solve_newton(b_z, b_l, b_q, rc_l, rc_q):
            """Solve P Δz + GᵀΔλ = b_z, GΔz + Δs = b_s, λ̃∘(W⁻ᵀΔs + WΔλ) = rc.

            Returns Δz, the rays' Δs, Δλ and the cones' scaled W⁻ᵀΔs, WΔλ (computed in the scaled space so that
            the linearised complementarity holds to rounding even when W is badly conditioned).
            """
            u_l = rc_l / lt_l
            t_l = -b_l + (s_l / lt_l) * u_l  # t = −b_s + Wᵀu
            w2t_l = w2_l * t_l
            if soc:
                u_q = cones.soc_div(lt_q, rc_q)
                t_q = -b_q + mv(Wq.mT, u_q)
                w2t_q = mv(w2_q, t_q)
            else:
                w2t_q = None
            # (P + GᵀW⁻²G)Δz = b_z − GᵀW⁻²t, WΔλ = W⁻ᵀ(GΔz + t), W⁻ᵀΔs = u − WΔλ
            dz = torch.cholesky_solve((b_z - GTy(w2t_l, w2t_q)).unsqueeze(-1), L).squeeze(-1)
            gdz_l, gdz_q = Gz(dz)
            dl_l = onl * (w2_l * gdz_l + w2t_l)
            ds_l = onl * (b_l - gdz_l)
            if soc:
                dlt_q = onf[..., None] * mv(Wq_inv.mT, gdz_q + t_q)
                dst_q = onf[..., None] * (u_q - dlt_q)
            else:
                dst_q = dlt_q = None
            return dz, ds_l, dl_l, dst_q, dlt_q

        def direction(rc_l, rc_q):
            """Newton direction for the current residuals, with one step of iterative refinement."""
            sol = solve_newton(-r_z, -r_l, -r_q if soc else None, rc_l, rc_q)
            dz, ds_l, dl_l, dst_q, dlt_q = sol
            # residuals of the unscaled equations, then one correction with the same factorisation
            dl_q = mv(Wq_inv, dlt_q) if soc else None
            ds_q = mv(Wq.mT, dst_q) if soc else None
            e_z = -r_z - (P @ dz.unsqueeze(-1)).squeeze(-1) - GTy(dl_l, dl_q)
            gdz_l, gdz_q = Gz(dz)
            e_l = onl * (-r_l - gdz_l - ds_l)
            e_q = onf[..., None] * (-r_q - gdz_q - ds_q) if soc else None
            ec_l = onl * (rc_l - lt_l * (ds_l * lt_l / s_l + dl_l * s_l / lt_l))
            ec_q = onf[..., None] * (rc_q - cones.soc_prod(lt_q, dst_q + dlt_q)) if soc else None
            corr = solve_newton(e_z, e_l, e_q, ec_l, ec_q)
            return tuple(a + b if a is not None else None for a, b in zip(sol, corr))

        def max_step(ds_l, dl_l, dst_q, dlt_q):
            """Largest step keeping s and λ in the cones (cones measured in the scaled variables)."""
            inf = torch.full_like(s_l, float("inf"))
            a = torch.minimum(
                torch.where(ds_l < 0, -s_l / ds_l.clamp_max(-1e-300), inf),
                torch.where(dl_l < 0, -lam_l / dl_l.clamp_max(-1e-300), inf),
            )
            if soc:
                a = torch.minimum(a, cones.soc_max_step(lt_q, dst_q))
                a = torch.minimum(a, cones.soc_max_step(lt_q, dlt_q))
            a = torch.where(on, a, inf)
            return a.amin(-1)

        # ---- predictor (affine scaling) ----
        rc_l = -lt_l * lt_l
        rc_q = -cones.soc_prod(lt_q, lt_q) if soc else None
        dz_a, ds_la, dl_la, ds_qa, dl_qa = direction(rc_l, rc_q)
        a_aff = max_step(ds_la, dl_la, ds_qa, dl_qa).clamp_max(1.0)
        aa = a_aff[:, None]
        gap_aff = onl * (s_l + aa * ds_la) * (lam_l + aa * dl_la)
        if soc:
            gap_aff = gap_aff + onf * ((lt_q + aa[..., None] * ds_qa) * (lt_q + aa[..., None] * dl_qa)).sum(-1)
        sigma = (gap_aff.sum(-1) / gap.clamp_min(1e-300)).clamp(0.0, 1.0) ** 3
        tau = (sigma * gap / degree)[:, None]

        # ---- corrector (Mehrotra): rc = −λ̃∘λ̃ + στe − (W⁻ᵀΔs_a)∘(WΔλ_a) ----
        rc_l = -lt_l * lt_l + tau - (ds_la * lt_l / s_l) * (dl_la * s_l / lt_l)
        if soc:
            corr_q = cones.soc_prod(ds_qa, dl_qa)
            rc_q = -cones.soc_prod(lt_q, lt_q) + tau[..., None] * cones.soc_identity((B, K), d, s_l) - corr_q
        dz, ds_l, dl_l, ds_q, dl_q = direction(rc_l, rc_q)
        alpha = (0.99 * max_step(ds_l, dl_l, ds_q, dl_q)).clamp_max(1.0)
        alpha = torch.where(run, alpha, torch.zeros_like(alpha))
        a1 = alpha[:, None]
        z = z + a1 * dz
        s_l = s_l + a1 * ds_l
        lam_l = lam_l + a1 * dl_l
        if soc:
            a2 = a1[..., None]
            s_tilde = lt_q + a2 * ds_q  # W⁻ᵀs⁺
            z_tilde = lt_q + a2 * dl_q  # Wλ⁺
            s_q = s_q + a2 * mv(Wq.mT, ds_q)
            lam_q = lam_q + a2 * mv(Wq_inv, dl_q)
            W_step, W_step_inv = cones.SocNTScaling(s_tilde, z_tilde).matrices()
            upd = (run[:, None] & on)[..., None, None]
            lt_q = torch.where(upd[..., 0], mv(W_step, z_tilde), lt_q)
            Wq = torch.where(upd, W_step @ Wq, Wq)
            Wq_inv = torch.where(upd, Wq_inv @ W_step_inv, Wq_inv)

    # Elements that stopped without converging: usable if their best residual is small.
    z = best["z"]
    not_conv = status == MAX_ITER
    status[not_conv & (best["res"] <= acceptable_tol)] = INACCURATE
    bad_numbers = not_conv & ~torch.isfinite(best["res"])
    status[bad_numbers] = NUMERICAL

    # ---- factor of H at the returned iterate, for the backward pass ----
    s_l, lam_l = best["s_l"], best["lam_l"]
    w2_l = onl * lam_l / s_l
    # The backward pass needs the symmetric NT scaling of the returned (s, λ): the accumulated W of the
    # iterations is only determined up to a Lorentz transformation, which changes WᵀW in the rotational
    # (tangent-to-the-cone) directions.
    if soc:
        _, w_inv = cones.SocNTScaling(best["s_q"], best["lam_q"]).matrices()
        w2_q = w_inv @ w_inv.mT
        if d == 3:
            w2_q = _fix_rotation(w2_q, best["s_q"], best["lam_q"])
    else:
        w2_q = None
    L, _ = _cholesky(assemble(w2_l, w2_q))
    return IPMResult(z=z, status=status, iterations=iterations, residual=best["res"], chol=L, w2_lin=w2_l)


def _fix_rotation(w2: torch.Tensor, s: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Set W⁻² in the direction that rotates the tangential part of a 3-D cone to its limit ‖λ_t‖/‖s_t‖.

    At a sliding contact s and λ lie on opposite rays of the cone boundary and turn together, so the
    linearised complementarity gives ds_rot = −(‖s_t‖/‖λ_t‖)·dλ_rot.  The NT scaling of an iterate that is not
    exactly centred gets this ratio only roughly; it is the one entry the backward pass is sensitive to.
    w2: (..., 3, 3); s, lam: (..., 3).
    """
    st = s[..., 1:]
    u = st / st.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    v = torch.zeros_like(s)
    v[..., 1] = -u[..., 1]
    v[..., 2] = u[..., 0]
    target = lam[..., 1:].norm(dim=-1) / st.norm(dim=-1).clamp_min(1e-300)
    current = (v * (w2 @ v.unsqueeze(-1)).squeeze(-1)).sum(-1)
    ok = (st.norm(dim=-1) > 0) & torch.isfinite(target)
    delta = torch.where(ok, target - current, torch.zeros_like(target))
    return w2 + delta[..., None, None] * v.unsqueeze(-1) * v.unsqueeze(-2)
