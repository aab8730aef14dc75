"""Would a closed form for a free rigid body speed up the box's dynamics? (An experiment; the package has no such
path.)

The box's vector field is the generic constrained Lagrangian one (``dynamics/lagrangian.py``): J_E, J̇_E, the 6 × 6
matrix J_E M⁻¹ J_Eᵀ and its Cholesky at every evaluation, about 44 % of a CubeToss training step (docs/speed.md).
For a free rigid body the same accelerations follow from Newton–Euler in the points' coordinates: with the axes
e_k = x_k − x_0, ω = ½ Σ e_k × ė_k, the force F = Σ f_i and the torque Σ e_k × f_k about the first point,

    a_G = F / m,  I_G ω̇ = τ_G − ω × I_G ω,  ë_k = ω̇ × e_k + ω × (ω × e_k),  a_0 = a_G − ω̇ × r − ω × (ω × r)

(r = Σ δ_k e_k the centre of mass from the first point, I_G = m R (tr S − S) Rᵀ with S = diag(μ) the second
moments per unit mass about it). This script checks the closed form against the generic field on random rigid
states (float64) and times both, forward and backward, at the training batch (float32, one thread), alternating.

    python investigations/rigid_field.py --batch 50 --repeats 200
    python investigations/rigid_field.py --tosses data/CubeToss --split val   # and whole tosses, both ways
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
import os
import time

import torch

from diffcontact import build_task
from diffcontact.dynamics.inertia import body_blocks
from diffcontact.dynamics.lagrangian import lagrangian_field, potential_force
from diffcontact.state import Inertia
from diffcontact.systems.poses import pose_to_points


def rigid_field(params, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(ẋ, v̇) of one free rigid body as 4 points x, v (B, 4, 3) by Newton–Euler (module docstring)."""
    inertia = params.inertia
    m, mom = inertia.masses[0], inertia.moments[0]
    com = inertia.com[0] if inertia.com is not None else torch.zeros_like(mom)
    f = potential_force(params, x)
    E, Edot = x[:, 1:] - x[:, :1], v[:, 1:] - v[:, :1]  # (B, 3, 3): rows are the body axes in the world
    omega = 0.5 * torch.linalg.cross(E, Edot).sum(1)  # (B, 3)
    F = f.sum(1)
    tau_c = torch.linalg.cross(E, f[:, 1:]).sum(1)
    r = com.to(x) @ E  # (B, 3)
    tau_g = tau_c - torch.linalg.cross(r, F)
    i_body = m * (mom.sum() - mom)  # (3,): principal moments about the centre of mass
    w_b = (E @ omega[..., None])[..., 0]  # (the body frame: components along the axes)
    t_b = (E @ tau_g[..., None])[..., 0]
    wdot_b = (t_b - torch.linalg.cross(w_b, i_body.to(x) * w_b)) / i_body.to(x)
    wdot = (wdot_b[:, None, :] @ E)[:, 0]
    a_g = F / m
    w, wd = omega[:, None, :].expand_as(E), wdot[:, None, :].expand_as(E)
    edd = torch.linalg.cross(wd, E) + torch.linalg.cross(w, torch.linalg.cross(w, E))
    a0 = a_g - torch.linalg.cross(wdot, r) - torch.linalg.cross(omega, torch.linalg.cross(omega, r))
    return v, torch.cat([a0[:, None], a0[:, None] + edd], dim=1)


def random_states(batch: int, dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid states: random poses (unit quaternions), velocities and body-frame spins."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(batch, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    x, v = pose_to_points(
        torch.randn(batch, 3, generator=g, dtype=torch.float64),
        q,
        torch.randn(batch, 3, generator=g, dtype=torch.float64),
        3 * torch.randn(batch, 3, generator=g, dtype=torch.float64),
    )
    return x.to(dtype), v.to(dtype)


def compare_tosses(data: str, split: str, task) -> dict:
    """The nominal model of ``task`` rolled out over the whole tosses of ``split`` (as ``evaluate`` does, float64)
    with the generic field and with the closed form: both metrics, and the largest difference of the predicted
    centres (m)."""
    import diffcontact.simulator as simulator
    from diffcontact.eval.tosses import predict_tosses, score_tosses
    from diffcontact.models.model import known_model

    generic = simulator.lagrangian_field
    out = {}
    try:
        for name in ("generic", "closed form"):
            if name == "closed form":
                simulator.lagrangian_field = lambda cons, params, x, v, Minv=None: rigid_field(params, x, v)
            start = time.perf_counter()
            predicted = predict_tosses(known_model(task), data, split)
            out[name] = score_tosses(predicted, data, split) | {"seconds": time.perf_counter() - start}
            out[name + " positions"] = predicted["position"]
    finally:
        simulator.lagrangian_field = generic
    a, b = out.pop("generic positions"), out.pop("closed form positions")
    out["max_position_difference_m"] = float(abs(a - b).max())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--com", type=float, nargs=3, default=(0.0007, 0.0003, 0.007), help="m, body frame")
    parser.add_argument("--tosses", default=None, help="an imported dataset: also roll its tosses out both ways")
    parser.add_argument("--split", default="val")
    args = parser.parse_args()
    torch.set_num_threads(1)
    task = build_task("CubeToss", {"body": {"centre_of_mass": list(args.com), "moments": [0.0015, 0.0016, 0.0017]}})
    cons = task.system.constraints
    out: dict = {"load_average": list(os.getloadavg())}

    params = task.params
    x, v = random_states(64, torch.float64)
    _, Minv = body_blocks(params.inertia)
    generic = lagrangian_field(cons, params, x, v, Minv=Minv)[1]
    closed = rigid_field(params, x, v)[1]
    out["max_difference_float64"] = float((generic - closed).abs().max() / generic.abs().max())

    i64 = params.inertia
    params32 = params.replace(inertia=Inertia(i64.masses.float(), i64.moments.float(), i64.com.float()))
    x, v = (t.requires_grad_(True) for t in random_states(args.batch, torch.float32, seed=1))

    def generic_step():
        _, Minv32 = body_blocks(params32.inertia)
        a = lagrangian_field(cons, params32, x, v, Minv=Minv32)[1]
        a.sum().backward()

    def closed_step():
        rigid_field(params32, x, v)[1].sum().backward()

    times: dict[str, list[float]] = {"generic": [], "closed form": []}
    for _ in range(3):  # (alternated: a shared machine's load moves both alike)
        for name, step in (("generic", generic_step), ("closed form", closed_step)):
            start = time.perf_counter()
            for _ in range(args.repeats):
                step()
            times[name].append((time.perf_counter() - start) / args.repeats * 1e3)
    out["ms_forward_backward"] = times
    out["ratio_of_medians"] = sorted(times["generic"])[1] / sorted(times["closed form"])[1]
    if args.tosses:
        out["tosses"] = compare_tosses(args.tosses, args.split, task)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
