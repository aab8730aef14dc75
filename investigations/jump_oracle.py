"""How much of a task's error a CLNN baseline can remove, with parts of the true velocity jump given to it.

    python investigations/jump_oracle.py BD5 --data data
    python investigations/jump_oracle.py BP5-e BP5 BD5 --split test

Every predictor below steps with the true smooth flow (the exact simulator's RK4 step with the true inertia and
potential: what a CLNN baseline's learned part is once it is right), then adds a velocity jump where the true
contact model changes the velocity.  The jump is the true one, Δv = v(true step) − v(flow), or a part of it:

- ``flow, no jump``: a baseline collapsed to "no velocity change at a collision" (the L1 collapse);
- ``flow + true jump``: a baseline that learned the jump exactly (0 up to the time of impact, which moves positions
  too on the tasks that use it);
- ``flow + jump on contact receivers``: Δv kept only on the points that a contact relation of the interaction
  networks reaches (``models.baselines.graphs``: a disk's centre, not its two axis points), zero on the others;
- ``flow + jump of the centres, rigidly``: each body's points get its centre's Δv (the jump's translation, without
  the change of spin that friction gives).

Each is scored as ``benchmarks/baselines_best.py`` scores a baseline: Fig. 3's 5-step error on the split's
trajectories and the one-step relative error on its pairs whose second frame holds a collision, beside a
constant-velocity predictor.  A part of the jump that does not beat constant velocity, given exactly, cannot make
a baseline that learns only that part beat it either.  Also printed: how the true jump's norm splits between the
receivers and the other points, and the jump's size on the pairs (from the split's 5-frame chunks, which a
window rule keeps off collision frames: on a rope, its first frames) against its size on the collisions of every
frame of the same trajectories.  float64, no training, seconds per task.

With ``--fit`` it also fits MLP-CD-CLNN's jump network alone (the published 2PD → 3 × 256 ReLU → PD, seeded as the
model seeds it) to the true jump, input [x, v] after the true flow, on the collision frames of the training
trajectories: as many as the baselines' training pairs hold (one 5-frame chunk per trajectory), and more, taken from
every frame of the same trajectories.  MSE (the loss under which the baselines learn part of the jump,
docs/baselines.md), AdamW at lr 1e-3, batch 50, ``--steps`` steps.  Scored every 250 steps on the collision frames
of every frame of the split's trajectories: the one-step relative error of flow + the fitted jump (best and last),
against flow without a jump.  That is a learning curve in the number of collisions the network sees.
"""

from __future__ import annotations

import diffcontact  # noqa: F401  (first: it sets OpenMP's wait policy, which torch reads when it loads)

# isort: split
import argparse
import json
from collections.abc import Callable
from pathlib import Path

import torch

from diffcontact import build_task, simulator_for
from diffcontact.data.dataset import PairDataset
from diffcontact.data.store import dataset_folder, load_split
from diffcontact.eval.metrics import mean_interval, relative_error, trajectory_error
from diffcontact.eval.rollouts import ground_truth
from diffcontact.models.baselines.base import mlp
from diffcontact.models.baselines.graphs import EQUALITY, relation_graph
from diffcontact.state import State

Jump = Callable[[torch.Tensor], torch.Tensor]  # Δv (B, P, d) -> the part given to the predictor


def receivers(system) -> torch.Tensor:
    """(P,) bool: the points that some contact relation of the interaction networks has as its receiver."""
    g = relation_graph(system)
    contact = g.slot != EQUALITY
    return (g.recv[contact, : system.n_points] != 0).any(0)


def rigid_centres(system) -> Jump:
    """Each body's points take its first point's (the centre's) Δv."""
    q = system.points_per_body
    return lambda dv: dv.view(dv.shape[0], -1, q, dv.shape[-1])[:, :, :1].expand(-1, -1, q, -1).reshape(dv.shape)


def oracle_step(sim, params, x, v, dt: float, part: Jump | None):
    """One frame: the true flow, then ``part`` of the true jump (None: the true step itself)."""
    state, _ = sim.step(State(x, v), params, dt)
    if part is None:
        return state.x, state.v
    x1, v1 = sim.flow(params, x, v, dt)
    return x1, v1 + part(state.v - v1)


def rollout(step, x0, v0, frames: int):
    xs, vs = [x0], [v0]
    for _ in range(frames - 1):
        x, v = step(xs[-1], vs[-1])
        xs.append(x)
        vs.append(v)
    return torch.stack(xs, 1), torch.stack(vs, 1)


def collision_frames(sim, params, s, dt: float):
    """Every frame of a split's trajectories whose next frame holds a collision: the true flow's state after one
    step from it (x1, v1) and the recorded next state (xt, vt), each (M, P, d)."""
    hit = s.contact[:, 1:]
    x0, v0, xt, vt = s.x[:, :-1][hit], s.v[:, :-1][hit], s.x[:, 1:][hit], s.v[:, 1:][hit]
    x1, v1 = sim.flow(params, x0, v0, dt)
    return x1, v1, xt, vt


def measure(task_name: str, data: str, split: str) -> dict:
    task = build_task(task_name)
    sim, params, system = simulator_for(task), task.params, task.system
    folder = dataset_folder(data, task_name)
    x, v, _, dt = ground_truth(folder, split, 5, task.config)
    split_data = load_split(folder, split, task.config)
    pairs = PairDataset(split_data)
    hit = pairs.collision
    px0, pv0, px1, pv1 = (t[hit].double() for t in (pairs.x0, pairs.v0, pairs.x1, pairs.v1))
    mask = receivers(system).to(torch.float64)[None, :, None]
    parts: dict[str, Jump | None] = {
        "flow + true jump": None,
        "flow, no jump": lambda dv: torch.zeros_like(dv),
        "flow + jump on contact receivers": lambda dv: dv * mask,
    }
    if system.points_per_body > 1:
        parts["flow + jump of the centres, rigidly"] = rigid_centres(system)
    predictors = {"constant velocity": lambda x_, v_: (x_ + dt * v_, v_)}
    for name, part in parts.items():
        predictors[name] = lambda x_, v_, part=part: oracle_step(sim, params, x_, v_, dt, part)
    rows = {}
    with torch.no_grad():
        for name, step in predictors.items():
            xh, vh = rollout(step, x[:, 0], v[:, 0], 5)
            mean, half = mean_interval(trajectory_error(relative_error(xh, vh, x, v), 5))
            qx, qv = rollout(step, px0, pv0, 2)
            one = relative_error(qx[:, 1:], qv[:, 1:], px1[:, None], pv1[:, None])[:, 0]
            rows[name] = {"five_step": mean, "ci95": half, "collision_pairs": float(one.mean())}
        x1, v1 = sim.flow(params, px0, pv0, dt)
        dv = pv1 - v1  # the true jump on the collision pairs (B, P, d)
        on = float((dv * mask).square().sum())
        share = on / float(dv.square().sum())
        size = dv.flatten(1).norm(dim=1)  # |Δv| over all points, per collision pair
        _, fv1, _, fvt = collision_frames(sim, params, split_data, dt)
        size_every = (fvt - fv1).flatten(1).norm(dim=1)
    return {
        "task": task_name,
        "split": split,
        "collision_pairs": int(hit.sum()),
        "receivers": int(mask.sum()),
        "points": system.n_points,
        "jump_share_on_receivers": share,
        "chunk_start_max": int(torch.as_tensor(split_data.chunk_start).max()),
        "jump_median_pairs": float(size.median()),
        "jump_zero_share_pairs": float((size <= 1e-9).double().mean()),
        "jump_median_every_frame": float(size_every.median()),
        "collisions_every_frame": int(fv1.shape[0]),
        "predictors": rows,
    }


def fit_curve(task_name: str, data: str, split: str, sizes: list[int], steps: int, seed: int) -> dict:
    """The jump MLP fitted alone on n training collisions for each n of ``sizes`` (0: the chunks' own)."""
    task = build_task(task_name)
    sim, params = simulator_for(task), task.params
    folder = dataset_folder(data, task_name)
    train, held = load_split(folder, "train", task.config), load_split(folder, split, task.config)
    dt = float(train.t[1] - train.t[0])

    chunk_pairs = PairDataset(train)
    with torch.no_grad():
        tx, tv, txt, tvt = collision_frames(sim, params, train, dt)
        hx, hv, hxt, hvt = collision_frames(sim, params, held, dt)
        cx0, cv0 = chunk_pairs.x0[chunk_pairs.collision], chunk_pairs.v0[chunk_pairs.collision]
        cx1, cv1 = sim.flow(params, cx0, cv0, dt)
        cvt = chunk_pairs.v1[chunk_pairs.collision]
        no_jump = float(relative_error(hx[:, None], hv[:, None], hxt[:, None], hvt[:, None])[:, 0].mean())
    D = tx[0].numel()
    curve = {"held_out_collisions": int(hx.shape[0]), "flow_no_jump": no_jump, "runs": []}
    for n in sizes:
        if n == 0:
            X, Y = torch.cat([cx1.flatten(1), cv1.flatten(1)], 1), (cvt - cv1).flatten(1)
        else:
            pick = torch.randperm(tx.shape[0], generator=torch.Generator().manual_seed(seed))[:n]
            X, Y = torch.cat([tx[pick].flatten(1), tv[pick].flatten(1)], 1), (tvt[pick] - tv[pick]).flatten(1)
        gen = torch.Generator().manual_seed(seed)
        net = mlp([2 * D, 256, 256, 256, D], gen).to(torch.float64)
        opt = torch.optim.AdamW(net.parameters(), lr=1e-3)
        held_in, held_dv = torch.cat([hx.flatten(1), hv.flatten(1)], 1), (hvt - hv).flatten(1)
        seen = slice(0, 2500)  # (the training error on at most 2,500 of the fitted collisions)
        points = []
        for k in range(steps + 1):
            if k % 250 == 0:
                with torch.no_grad():
                    vh = hv + net(held_in).view_as(hv)
                    err = relative_error(hx[:, None], vh[:, None], hxt[:, None], hvt[:, None])[:, 0].mean()
                    r2 = 1 - (net(held_in) - held_dv).square().sum() / held_dv.square().sum()
                    r2_fit = 1 - (net(X[seen]) - Y[seen]).square().sum() / Y[seen].square().sum()
                points.append((k, float(err), float(r2), float(r2_fit)))
            if k == steps:
                break
            idx = torch.randint(0, X.shape[0], (50,), generator=gen)
            loss = (net(X[idx]) - Y[idx]).square().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        best = min(points, key=lambda p: p[1])
        curve["runs"].append({"collisions": int(X.shape[0]), "chunks": n == 0, "best": best, "last": points[-1],
                              "curve": points})  # fmt: skip
    return curve


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tasks", nargs="+")
    ap.add_argument("--data", default="data", help="root of the generated datasets (diffcontact generate TASK)")
    ap.add_argument("--split", default="val", choices=("train", "val", "test"))
    ap.add_argument("--fit", action="store_true", help="also the learning curve of MLP-CD-CLNN's jump network alone")
    ap.add_argument("--sizes", default="0,2000,8000,30000", help="training collisions for --fit (0: the chunks')")
    ap.add_argument("--steps", type=int, default=4000, help="AdamW steps of each --fit run")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="also write every figure here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = [measure(t, args.data, args.split) for t in args.tasks]
    if args.fit:
        sizes = [int(s) for s in args.sizes.split(",")]
        for r in out:
            r["fit"] = fit_curve(r["task"], args.data, args.split, sizes, args.steps, args.seed)
    for r in out:
        print(
            f"\n{r['task']} ({r['split']}): {r['collision_pairs']} collision pairs; contact relations reach "
            f"{r['receivers']} of {r['points']} points, which carry {100 * r['jump_share_on_receivers']:.1f} % of "
            "the true jump's squared norm on those pairs"
        )
        print(
            f"the true jump |Δv| (over all points) on those pairs, from chunks starting at frames 0–"
            f"{r['chunk_start_max']}: median {r['jump_median_pairs']:.3g} m/s, "
            f"{100 * r['jump_zero_share_pairs']:.0f} % below 1e-9; on the {r['collisions_every_frame']} collisions of "
            "every frame: median "
            f"{r['jump_median_every_frame']:.3g} m/s"
        )
        print("| predictor | 5-step error | collision pairs |\n|---|---|---|")
        for name, p in r["predictors"].items():
            print(f"| {name} | {p['five_step']:.4g} ± {p['ci95']:.2g} | {p['collision_pairs']:.4g} |")
        if "fit" in r:
            f = r["fit"]
            print(
                f"\nMLP jump alone, MSE, lr 1e-3, {args.steps} steps; one-step error on {f['held_out_collisions']} "
                f"held-out collision frames (flow, no jump: {f['flow_no_jump']:.4g})"
            )
            print(
                "| training collisions | error, best (step) | error, last | R² of Δv held out, last "
                "| R² of Δv fitted, last |\n|---|---|---|---|---|"
            )
            for run in f["runs"]:
                label = f"{run['collisions']}" + (" (the baselines' chunks)" if run["chunks"] else "")
                b, last = run["best"], run["last"]
                print(f"| {label} | {b[1]:.4g} ({b[0]}) | {last[1]:.4g} | {last[2]:.3f} | {last[3]:.3f} |")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
